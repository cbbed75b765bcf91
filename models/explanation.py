"""What each part of a refined model does: its coefficients, and how much of the output it carries.

A NARX model's output is a sum over its terms, y[t] = Σᵢ θᵢ·φᵢ[t]. The terms fall into groups: those
of the declared structure (with nothing declared, the linear start the loop chose) and those each
effect the loop added brought. A group G's **contribution** is its part of that sum,

    c_G[t] = Σ_{i∈G} θᵢ·φᵢ(x, ŷ)[t]        [the output's unit],

with the regressors φ evaluated along the model's own free run ŷ over a record (what the model
makes of that record from its input alone), or along the measured output where the free run
diverged (the one-step regressors; diverged: not finite, or beyond ``RESTLESS`` times the
largest measured output, :func:`models.output_error.diverged`). Its **share** is
RMS(c_G) / RMS(y), y the measured output over the same samples: how large a part of each
sample's equation the group supplies. The groups' contributions sum to the
model's output before any output limit; the shares need not sum to 1, as the groups'
contributions partly cancel (a hardening spring pulls against the linear part's swing).

A recursion's share is per step: an effect that supplies a thousandth of each step's output can
move the free run by far more, as the steps add up (finely sampled dynamics: each step's force
term is scaled by the squared sampling interval). So each effect also has its **removal**: with
ŷ₋_G the model's free run with the effect's coefficients set to zero (its limits lifted, for
saturation),

    removal_G = RMS(ŷ − ŷ₋_G) / RMS(y)        [a share; infinite where ŷ₋_G diverges],

how much of the output the model's own simulation owes to the effect.

Each group's coefficients come with their standard errors where the model has a covariance
(least squares' σ̂²(ΦᵀΦ)⁻¹, output error's σ̂²(JᵀJ)⁻¹); a theoretical model has none. Two
families bring no terms to the process model: moving-average noise (its coefficients c_k of the
residual e[t-k] shape the one-step predictions, not the free run: no share), and output
saturation (its limits, the share of the run's samples that lie at one, and its removal).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from models.effects import RECTIFIED
from models.metrics import rms
from models.narx import NARX
from models.output_error import diverged
from models.refinement import Refinement
from models.scoring import EffectScore
from models.terms import parse_terms, regressor_matrix

Along = Literal["free run", "one-step"]
_NOISE_TERM = re.compile(r"e\[t-(\d+)\]")


@dataclass(frozen=True)
class Contribution:
    """One group of a model's terms: their names and coefficients (with standard errors, None
    where the model has no covariance), the group's contribution c_G over the scored samples
    [the output's unit] and its share RMS(c_G) / RMS(y) (None for moving-average noise, which
    the free run does not hold). For output saturation, ``limits`` (low, high) and the share
    of the scored samples at one, ``at_limits``. ``removal``: how far the free run moves
    without the effect (infinite where it then diverges; None where not run)."""

    terms: tuple[str, ...]
    coefficients: tuple[float, ...]
    standard_errors: tuple[float, ...] | None
    series: np.ndarray
    share: float | None
    limits: tuple[float, float] | None = None
    at_limits: float | None = None
    removal: float | None = None

    @property
    def rms(self) -> float | None:
        """RMS of the contribution [the output's unit]; None where the group has none."""
        return rms(self.series) if self.series.size else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible, without the series; infinite limits as None."""
        document: dict[str, Any] = {
            "terms": list(self.terms),
            "coefficients": list(self.coefficients),
            "standard_errors": None if self.standard_errors is None else list(self.standard_errors),
            "rms": self.rms,
            "share": self.share,
            "removal_share": self.removal if self.removal is None or np.isfinite(self.removal) else None,
            "diverges_without": self.removal == np.inf,
        }
        if self.limits is not None:
            document["limits"] = [v if np.isfinite(v) else None for v in self.limits]
            document["at_limits"] = self.at_limits
        return document


@dataclass(frozen=True)
class Explanation:
    """A model's groups on one record: ``declared`` (the declared structure's terms), one
    contribution for each effect added, in order, the output's RMS over the scored samples,
    what the regressors were evaluated along, and ``first``, the record's sample that each
    series' first value belongs to."""

    declared: Contribution
    effects: tuple[Contribution, ...]
    output_rms: float
    along: Along
    first: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: the declared part's contribution and the record's figures; each
        effect's is its own (:meth:`Contribution.to_dict`)."""
        return {"along": self.along, "output_rms": self.output_rms, "declared": self.declared.to_dict()}

    def into(self, document: dict[str, Any]) -> None:
        """Put the explanation into a refinement report's document
        (:meth:`models.refinement.RefinementReport.to_dict`): each effect added gets its
        ``contribution``, and the document an ``explanation`` (:meth:`to_dict`)."""
        for effect, contribution in zip(document["effects_added"], self.effects, strict=True):
            effect["contribution"] = contribution.to_dict()
        document["explanation"] = self.to_dict()


def explain(
    model: NARX,
    effects: Sequence[EffectScore],
    x: np.ndarray,
    y: np.ndarray,
    initial: int = 0,
    t0: int = 0,
    transient: int = 0,
    noise: np.ndarray | None = None,
) -> Explanation:
    """Each of ``effects``' contribution to ``model`` on the record (x, y), and the declared
    part's (every term no effect brought), as the module docstring defines them.

    The record is run as :func:`models.assessment.assess` runs it: the first ``initial``
    samples (at least the model's lags) start the free run, ``t0`` places the record in the
    time base of sinusoidal terms, and the first ``transient`` samples are run through but not
    scored. ``noise`` are the model's moving-average coefficients c_1 … c_q, if any.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    lag = model.max_lag
    start_up = max(initial, lag)
    start = start_up - lag
    scored = lag + max(start_up, transient) - start_up  # the first scored sample of xs and ys
    xs, ys = x[start:], y[start:]
    simulated = model.simulate(xs, ys, t0 + start)
    along: Along = "one-step" if diverged(simulated[scored:], ys[scored:]) else "free run"
    regressors, _ = regressor_matrix(
        model.terms, xs, simulated if along == "free run" else ys, lag, t0 + start
    )
    regressors = regressors[scored - lag :]
    scale = rms(ys[scored:])
    errors = model.standard_errors() if np.any(model.covariance) else None
    names = model.term_names

    def removal(without: NARX) -> float | None:
        """How far ``without``'s free run lies from the model's, as a share of the output's RMS."""
        if along != "free run" or not scale > 0:
            return None
        run = without.simulate(xs, ys, t0 + start)[scored:]
        return np.inf if diverged(run, ys[scored:]) else rms(run - simulated[scored:]) / scale

    def group(columns: list[int]) -> Contribution:
        series = regressors[:, columns] @ model.theta[columns]
        return Contribution(
            tuple(names[i] for i in columns),
            tuple(float(model.theta[i]) for i in columns),
            None if errors is None else tuple(float(errors[i]) for i in columns),
            series,
            rms(series) / scale if scale > 0 else None,
        )

    contributions, claimed = [], set()
    for effect in effects:
        if effect.noise_lags:
            contributions.append(_noise(effect, noise))
        elif not effect.terms:
            at_limits = _at_limits(model, simulated[scored:]) if along == "free run" else None
            without = removal(replace(model, output_limits=None))
            contributions.append(
                Contribution((), (), None, np.empty(0), None, model.output_limits, at_limits, without)
            )
        else:
            # The rectifier's label names no term: without it, the model reads its recursion's
            # output itself.
            brought = [name for name in effect.terms if name != RECTIFIED]
            columns = [names.index(term.name) for term in parse_terms(brought) if term.name in names]
            claimed.update(columns)
            theta = model.theta.copy()
            theta[columns] = 0.0
            rectified = model.rectified and RECTIFIED not in effect.terms
            without = replace(model, theta=theta, rectified=rectified)
            contributions.append(replace(group(columns), removal=removal(without)))
    declared = group([i for i in range(len(names)) if i not in claimed])
    return Explanation(declared, tuple(contributions), scale, along, start + scored)


def explain_refinement(
    refinement: Refinement,
    x: np.ndarray,
    y: np.ndarray,
    initial: int = 0,
    t0: int = 0,
    transient: int = 0,
) -> Explanation:
    """The refined model's effects added, explained on (x, y) as :func:`explain` does: the
    record a report judges the refined model on first, started and scored as it was."""
    return explain(
        refinement.refined, refinement.effects_added, x, y, initial, t0, transient, refinement.noise
    )


def _noise(effect: EffectScore, noise: np.ndarray | None) -> Contribution:
    """Moving-average noise's coefficients c_k of its terms e[t-k] (those the model holds)."""
    coefficients = np.empty(0) if noise is None else noise
    held = []
    for term in effect.terms:
        found = _NOISE_TERM.fullmatch(term)
        if found and 0 < (k := int(found.group(1))) <= coefficients.size:
            held.append((term, float(coefficients[k - 1])))
    return Contribution(tuple(t for t, _ in held), tuple(c for _, c in held), None, np.empty(0), None)


def _at_limits(model: NARX, run: np.ndarray) -> float | None:
    """The share of the free run's samples at one of the model's output limits."""
    limits = model.output_limits
    if limits is None or not run.size:
        return None
    return float(np.mean((run <= limits[0]) | (run >= limits[1])))
