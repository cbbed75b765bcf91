"""A baseline's terms chosen for a structure from its healthy records.

A monitoring baseline is judged by how well it simulates the structure, so its terms are chosen
on the simulation of held-out data, as the refinement loop chooses its start:

1. the linear orders and the input delay (0, which lets x[t] drive an acceleration, or 1) by
   :func:`models.refinement.choose_linear` with no margin: the linear model that simulates the
   held-out parts best, not the smallest near it, which the loop's start wants;
2. nonlinear terms offered by FROLS (:func:`models.selection.select_narx`, BIC along the path)
   from the monomials of the most recent lags, the linear terms kept; the prefixes of what it
   adds, in its order, are judged on the same held-out parts, and the best is kept only where it
   lowers their free-run error by more than that figure's standard error
   (:func:`models.checking.check_noise`): a term the one-step error likes but the simulation
   does not would only make the baseline a worse simulator.

Its cost grows with the records' length alone: a caller prices it as samples × ``CHOICE_COLUMNS``
before reading a signal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.candidates import candidate_terms
from models.checking import MIN_BLOCK, CheckSplit, Structure, check_noise
from models.effects import linear_terms
from models.refinement import choose_linear
from models.scoring import Records
from models.selection import select_narx
from models.signals import checked_records
from models.terms import Term, max_lag

# The monomials offered beyond the linear terms: up to this degree, of y and x at the most recent
# NONLINEAR_LAGS lags (a stiffness or damping nonlinearity acts on the current state, which the
# first lags carry), with the constant (an offset). Two lags were too few for the rig: its cubic
# spring, offered on y[t-1] and y[t-2] only, left a k2 fault mode trained on the chosen terms
# unable to describe a loosened k2 (its residual not white), where three lags describe it.
NONLINEAR_DEGREE = 3
NONLINEAR_LAGS = 3
# The largest linear order tried: that of a structure of three modes (the 3-DOF chain's), which
# covers the few modes a monitored response is dominated by; higher orders chase the sensor noise
# more than the dynamics, and the choice's cost grows with the square of this order.
MAX_ORDER = 6
# The most nonlinear terms the selection may add: each one judged is an output-error search.
MAX_ADDED = 4
_OFFERED = len(candidate_terms(NONLINEAR_DEGREE, NONLINEAR_LAGS, NONLINEAR_LAGS, 0)) - 2 * NONLINEAR_LAGS
# What the choice costs a sample, in cells (a sample times a column of a least-squares fit), over
# every fit it makes: each linear candidate of choose_linear on its three folds' fit parts (two
# thirds of the samples each), the FROLS dictionary, and each grown structure judged. The
# output-error searches that follow the fits grow with the same columns and samples.
CHOICE_COLUMNS = (
    2 * sum(2 * n for n in range(1, MAX_ORDER + 1)) * 2
    + 2 * MAX_ORDER
    + _OFFERED
    + MAX_ADDED * (2 * MAX_ORDER + MAX_ADDED)
)
# The fewest samples of each record: the check split's held-out blocks (a third of a record or of
# its blocks, or whole records from three on) are then longer than the largest order's lags.
CHOICE_MIN_SAMPLES = 3 * MIN_BLOCK
# The most terms a chosen baseline can have.
MAX_CHOSEN_TERMS = 2 * MAX_ORDER + MAX_ADDED


@dataclass(frozen=True)
class BaselineChoice:
    """The terms chosen and why: the linear orders ``ny`` = ``nx`` and input ``delay`` by the
    held-out simulation, the nonlinear terms that lowered it (``added``, empty where none did),
    and the chosen structure's free-run RMS over the held-out parts with its NRMSE (that RMS over
    the held-out outputs' standard deviation)."""

    terms: tuple[Term, ...]
    ny: int
    nx: int
    delay: int
    added: tuple[Term, ...]
    held_out_rms: float
    held_out_nrmse: float
    held_out_samples: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible, as a training reports it; a diverged free run's figures become None."""
        return {
            "terms": [term.name for term in self.terms],
            "orders": {"ny": self.ny, "nx": self.nx},
            "delay": self.delay,
            "terms_added": [term.name for term in self.added],
            "held_out": {
                "free_run_rms": _finite(self.held_out_rms),
                "free_run_nrmse": _finite(self.held_out_nrmse),
                "samples": self.held_out_samples,
            },
        }


def choose_baseline_terms(records: Records, max_order: int = MAX_ORDER) -> BaselineChoice:
    """The terms of a baseline for the structure the healthy ``records`` (x, y pairs) come from
    (module docstring)."""
    records = list(checked_records(records, CHOICE_MIN_SAMPLES, degree=NONLINEAR_DEGREE))
    checks = CheckSplit.of(records)
    (ny, nx, delay), linear = choose_linear(records, max_order, checks=checks, margin=0.0)
    lags = min(ny, NONLINEAR_LAGS)
    offered = [
        term
        for term in candidate_terms(NONLINEAR_DEGREE, lags, lags, delay)
        # The linear start's own terms (its constant among them) are not offered again.
        if term.degree != 1 and term not in linear and max_lag((term,)) <= max_lag(linear)
    ]
    selection = select_narx(
        records, (*linear, *offered), criterion="bic", include=linear, max_terms=len(linear) + MAX_ADDED
    )
    added = tuple(term for term in selection.model.terms if term not in linear)
    chosen = Structure(linear)
    figure = _simulated(checks, chosen)
    if added:
        grown = [Structure(linear + added[:k]) for k in range(1, len(added) + 1)]
        figures = [_simulated(checks, structure) for structure in grown]
        best = int(np.argmin(figures))
        if figures[best] < (1 - check_noise(checks.check)) * figure:
            chosen, figure = grown[best], figures[best]
    lag = max_lag(chosen.terms)
    held = np.concatenate([y[lag:] for _, y, _ in checks.check if len(y) > lag])
    spread = float(np.std(held)) if held.size else 0.0
    return BaselineChoice(
        chosen.terms,
        ny,
        nx,
        delay,
        chosen.terms[len(linear) :],
        figure,
        figure / spread if spread > 0 else np.inf,
        int(held.size),
    )


def choose_delay(records: Records, ny: int, nx: int) -> tuple[int, dict[int, float]]:
    """The input delay of a dictionary of ``ny`` output and ``nx`` input lags: 0 (x[t] … x[t-nx+1])
    or 1 (x[t-1] … x[t-nx]), as :func:`models.refinement.choose_linear` judges a delay: each one's
    linear ARX(ny, nx) run free over the held-out parts of the three rotations of the check split,
    and 0, the extra x[t], only where its mean figure is lower by more than the standard error of
    their difference across the rotations, or where only it simulates every rotation without
    diverging. Returns the delay and each one's mean free-run RMS
    (infinite where a model diverged). An acceleration feels the force at once: without x[t] its
    model has to predict a force it has not seen."""
    records = list(checked_records(records, 1))
    folds = [CheckSplit.of(records, fold) for fold in (1, 0, 2)]
    figures = {
        delay: np.array([_simulated(checks, Structure(linear_terms(ny, nx, delay))) for checks in folds])
        for delay in (1, 0)
    }
    if not np.all(np.isfinite(figures[0])):
        delay = 1
    elif not np.all(np.isfinite(figures[1])):
        delay = 0  # only x[t] keeps the model from diverging
    else:
        gain = figures[1] - figures[0]
        delay = 0 if float(np.mean(gain)) > float(np.std(gain, ddof=1) / np.sqrt(gain.size)) else 1
    return delay, {d: float(np.mean(values)) for d, values in figures.items()}


def _simulated(checks: CheckSplit, structure: Structure) -> float:
    """The held-out free-run RMS of ``structure``, its parameters by least squares or by output
    error, whichever simulates better (as :func:`choose_linear` judges the linear orders)."""
    return min(checks.error(structure), checks.error(structure, tuned=True))


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None
