"""Output-error refinement: NARX parameters that minimise the free-run (simulation) error.

Least squares on the one-step error (equation error) is biased when the output is measured with
noise: the noisy past outputs in the regressors attenuate the autoregressive coefficients (an
errors-in-variables bias that no added term can repair). Minimising the simulation error

    V(θ) = Σ_r Σ_{t ≥ L} (y_r[t] − ŷ_r[t; θ])²,

where ŷ_r is the model's free run driven by the input alone and started from the first L
measured outputs of record r, is consistent when the noise is on the output (Ljung, *System
Identification*, 2nd ed., §4.2: output-error models; Piroddi & Spinelli 2003 for polynomial
NARX). V is not quadratic in θ, so it is minimised by MINPACK's Levenberg–Marquardt search
(:mod:`models.levenberg_marquardt`, as ``scipy.optimize.least_squares`` runs it) from the
equation-error estimate. A parameter vector whose free run diverges is never accepted: its
residuals are replaced by a penalty larger than any finite run's, so the search steps back.

Nor is one whose free run does not come to rest when the excitation stops (:class:`RingDowns`),
where the start's does: a structure left to itself rings down. Polynomial terms tuned on the
simulation error can keep a free run bounded while the input drives it and yet make the
unforced model unstable: F-16's sweeps end in a few hundred samples of zero force, and a model of
acceleration 1 (cubic damping terms over ten lags) diverged there on two test levels.

Nor is one that diverges when its free run starts from measured outputs elsewhere in the
records, where the start's does not: every validation starts a free run so, and a model stable
only along its own trajectory from the records' first samples fails there (but for a state the
model's linear part rings from far beyond the records' range: :meth:`RingDowns.holds`). The
search is held to that only when its end fails it, and is then run again from the start: on the
way to a model that holds from every measured state it may pass through θ that do not.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg

from models.errors import InputError
from models.levenberg_marquardt import Search, minimise
from models.narx import NARX, run_start, sensor_limits
from models.regression import Workers, triangular_factor
from models.signals import checked_records
from models.simulation import FreeRun
from models.terms import Term, max_degree, max_lag, record_origins


@dataclass(frozen=True)
class OutputErrorFit:
    """The output-error model and how the free-run error moved.

    Attributes
    ----------
    model : the refined NARX; its covariance is σ̂²(JᵀJ)⁻¹ from the Jacobian J of the free-run
        residuals at the optimum, σ̂² = V/(n − p).
    start_rms, rms : free-run RMS over the records before (equation-error start) and after, in
        the output's units.
    evaluations : free runs computed by the search (over its fresh starts, each after MINPACK
        stopped at its step-size test having met the penalty, and over its second search, held
        to the restarts from measured outputs, where the first ended at θ that diverge there;
        and over the search from its end with a cancelled pole taken out, where there was one).
    status : the search's termination status as ``scipy.optimize.least_squares`` reports it
        (> 0: converged). The search is Levenberg–Marquardt (MINPACK,
        :mod:`models.levenberg_marquardt`), on the free-run error folded to p + 1 rows (‖r‖·e₁, and
        at the points kept the triangular factor of J, rotated): the same steps as on the tall
        residual, without MINPACK's own QR of the tall Jacobian, which cost half of Silverbox's
        searches.
    """

    model: NARX
    start_rms: float
    rms: float
    evaluations: int
    status: int


def fit_output_error(
    start: NARX,
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    max_evaluations: int = 200,
    t0: int | Sequence[int] = 0,
    threads: Workers = map,
    start_from: Literal["measured", "estimated"] = "measured",
) -> OutputErrorFit:
    """Refine ``start`` (an equation-error fit, say) by minimising its free-run error on ``records``.

    Parameters
    ----------
    start : the model whose terms are kept and whose θ starts the search; its free run must not
        diverge on any record.
    records : (x, y) pairs in the units of the model; each free run starts from its record's
        first L = ``start.max_lag`` measured outputs (a sensor-saturating model's from its first
        L clear of the sensor's limits, :func:`models.narx.run_start`).
    max_evaluations : bound on the search's evaluations of V (each a free run on every record;
        the Jacobian comes from the runs' sensitivities, one more pass per iteration); twice
        that where the search is run again, held to the restarts from measured outputs.
    t0 : where each record starts in the time base of sinusoidal terms (one for all, or one a
        record).
    threads : a map over threads of this process (:data:`models.regression.Workers`) that
        factors the Jacobian's blocks (:func:`models.regression.triangular_factor`); the fit is
        the same whichever.
    start_from : ``measured``, each free run starts from its record's first L measured outputs;
        ``estimated``, from the start that minimises its error over the record
        (:class:`EstimatedStart`: for a model linear in its output, whose runs are then to be
        started so, as :func:`estimated_start_error` does). From the estimated start, a search
        that ends with a slow pole a zero cancels is run again from its end with the pair taken
        out (:func:`without_cancelled_poles`), and its end is the fit where it is lower and has
        no such pair.

    Returns
    -------
    OutputErrorFit; its ``rms`` is never above ``start_rms`` (the start is kept if the search
    finds nothing better).

    Examples
    --------
    >>> import numpy as np
    >>> from models.narx import fit_narx
    >>> rng = np.random.default_rng(0)
    >>> x = rng.standard_normal(3000)
    >>> y = np.zeros(3000)
    >>> for t in range(2, 3000):
    ...     y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + x[t - 1]
    >>> noisy = y + 0.5 * rng.standard_normal(3000)  # measurement noise on the output
    >>> start = fit_narx([(x, noisy)], ["y[t-1]", "y[t-2]", "x[t-1]"])
    >>> fit = fit_output_error(start, [(x, noisy)])
    >>> bool(fit.rms < fit.start_rms)
    True
    """
    records = list(records)
    fit = _searched(start, records, max_evaluations, t0, threads, start_from)
    untangled = without_cancelled_poles(fit.model) if start_from == "estimated" else None
    if untangled is None:
        return fit
    try:
        again = _searched(untangled, records, max_evaluations, t0, threads, start_from)
    except InputError:  # its free run diverges where the fit's did not: the fit stands
        return fit
    evaluations = fit.evaluations + again.evaluations
    # Where the search from there ends in another such pair, the choice between the two would be
    # made by the noise their starts absorb: the first stands.
    if again.rms < fit.rms and without_cancelled_poles(again.model) is None:
        return OutputErrorFit(again.model, fit.start_rms, again.rms, evaluations, again.status)
    return replace(fit, evaluations=evaluations)


def _searched(
    start: NARX,
    records: Sequence[tuple[ArrayLike, ArrayLike]],
    max_evaluations: int,
    t0: int | Sequence[int],
    threads: Workers,
    start_from: Literal["measured", "estimated"],
) -> OutputErrorFit:
    """:func:`fit_output_error`'s search from one start."""
    search = _Search.build(start, records, t0, threads, start_from)
    # The search's start must run free and stay finite; where it does not come to rest either, the
    # search cannot be held to that; nor to the restarts from measured outputs where the start
    # does not hold from them.
    outputs = search.simulated(start.theta)
    initial = search.errors(outputs)
    if not np.all(np.isfinite(initial)):
        raise InputError(
            "the free run of the starting model diverges on the estimation data: output-error "
            "refinement needs a starting model whose simulation is stable"
        )
    search.at_rest = search.settles(start.theta, outputs)
    held = search.ring_downs.holds(start, start.theta, start.theta)
    # What a diverged run costs: every residual at a hundred times the output's RMS, far above
    # anything a finite run reaches, so that the search backs away from an unstable θ.
    search.penalty = 100.0 * (search.scale + float(np.max(np.abs(initial))))

    # The search is held to the restarts from measured outputs only where its end does not hold
    # from them: on its way to a model that does, it may pass through θ that do not (held from the
    # start, the search on the rig's record above stops at 38.5 mm, not 2.8).
    theta, result, evaluations = search.run(max_evaluations, holding=False)
    holds = not held or search.ring_downs.holds(start, theta, start.theta)
    if not holds:
        theta, result, more = search.run(max_evaluations, holding=True)
        evaluations += more
        holds = search.ring_downs.holds(start, theta, start.theta)
    return search.outcome(theta, result, evaluations, initial, holds)


@dataclass(eq=False)
class _Search:
    """:func:`fit_output_error`'s search over θ for one start and its records: the records'
    free runs prepared once (each θ then costs only the compiled recursion), what judges a θ, and
    the buffers MINPACK's calls share.

    Mutable, as the calls of one search share it: ``penalised_steps`` counts the θ met with the
    penalty (a fresh search starts where MINPACK crawled after one), and ``last`` keeps the
    residual at the θ last run, whose sensitivities the buffers hold, and ``settled`` whether each
    θ asked about comes to rest. ``at_rest`` and ``penalty`` are set from the start's own free
    run before the search.
    """

    start: NARX
    runs: list[tuple[FreeRun, np.ndarray]]  # each record's prepared free run and measured output
    ring_downs: RingDowns
    start_from: Literal["measured", "estimated"]
    threads: Workers
    scale: float  # the measured outputs' RMS (one where they are all zero)
    lag: int  # the model's largest lag (asked for at every θ tried)
    longest: int  # samples of the longest record
    # The Jacobian's buffers: each record's sensitivities, and the scaled Jacobian beside the
    # residual that is factored (a fresh array of Silverbox's 65 000 × 51 costs 4 ms in its
    # pages' first writes, about a tenth of the sensitivities).
    derivatives: list[np.ndarray]
    augmented: np.ndarray
    rows: np.ndarray  # where each record's block starts in ``augmented``, and the end
    at_rest: bool = False  # the start comes to rest, and so must every θ
    penalty: float = math.inf
    penalised_steps: int = 0
    last: dict[bytes, np.ndarray] = field(default_factory=dict)
    # Whether each θ asked about comes to rest: the start is asked before the search and again as
    # its first evaluation, the end again as the outcome.
    settled: dict[bytes, bool] = field(default_factory=dict)

    @classmethod
    def build(
        cls,
        start: NARX,
        records: Iterable[tuple[ArrayLike, ArrayLike]],
        t0: int | Sequence[int],
        threads: Workers,
        start_from: Literal["measured", "estimated"],
    ) -> _Search:
        L = start.max_lag
        checked = checked_records(records, L + len(start.terms) + 1, degree=max_degree(start.terms))
        origins = record_origins(t0, len(checked))
        # A sensor's clipped readings are no state to start from: each run starts clear of its
        # limits, as the check blocks and the tails judge it (models.narx.run_start).
        skips = [run_start(ya, L, sensor_limits(start)) - L for _, ya in checked]
        checked = [(xa[skip:], ya[skip:]) for (xa, ya), skip in zip(checked, skips, strict=True)]
        origins = [origin + skip for origin, skip in zip(origins, skips, strict=True)]
        targets = [ya[L:] for _, ya in checked]
        scale = np.sqrt(sum(float(np.sum(t**2)) for t in targets) / sum(t.size for t in targets)) or 1.0
        record_runs, ring_downs = prepared(start.terms, checked, origins)
        runs = [(run, ya) for run, (_, ya) in zip(record_runs, checked, strict=True)]
        if start_from == "estimated" and not start.reads_state:
            raise InputError(
                "the free run's start can be estimated only for a model that reports its recursion's "
                "output (no sensor limits, no magnitude)"
            )
        p = start.theta.size
        return cls(
            start=start,
            runs=runs,
            ring_downs=ring_downs,
            start_from=start_from,
            threads=threads,
            scale=scale,
            lag=L,
            longest=max(run.n for run, _ in runs),
            derivatives=[np.empty((run.n, p)) for run, _ in runs],
            augmented=np.empty((sum(run.n - L for run, _ in runs), p + 1)),
            rows=np.cumsum([0] + [run.n - L for run, _ in runs]),
        )

    @property
    def state(self) -> tuple[float, float] | None:
        """The limits the recursion's state saturates at (None where only a sensor's reading
        is clipped, or nothing is)."""
        return self.start.output_limits if self.start.saturation == "state" else None

    def started(self, theta: np.ndarray) -> tuple[EstimatedStart | None, list[np.ndarray]]:
        """Each record's output with the start its free run is to begin from."""
        if self.start_from == "measured":
            return None, [ya for _, ya in self.runs]
        estimated = EstimatedStart.of(self.start.terms, theta, self.longest)
        return estimated, [estimated.start(ya, run.run(theta, ya)) for run, ya in self.runs]

    def simulated(self, theta: np.ndarray) -> list[np.ndarray]:
        starts = self.started(theta)[1]
        return [self.start.run_free(run, ya, theta) for (run, _), ya in zip(self.runs, starts, strict=True)]

    def errors(self, outputs: list[np.ndarray]) -> np.ndarray:
        L = self.lag
        return np.concatenate([out[L:] - ya[L:] for out, (_, ya) in zip(outputs, self.runs, strict=True)])

    def settles(self, theta: np.ndarray, outputs: list[np.ndarray]) -> bool:
        """Whether θ's free run, ``outputs``, rings down after every switch-off."""
        key = theta.tobytes()
        if key not in self.settled:
            states = recursion_states(self.start, theta, self.runs, outputs)
            self.settled[key] = self.ring_downs.settle(self.start, theta, states)
        return self.settled[key]

    def sensitive(self, theta: np.ndarray) -> list[np.ndarray]:
        """The free runs (what :meth:`simulated` reports) with their exact sensitivities written
        into the buffers (one pass a record): MINPACK asks for the Jacobian at the θ it has just
        run whenever it keeps the step, nearly every step, and a run alone costs half a run with
        sensitivities (22 against 47 ms on Silverbox's 65 000 × 51). The penalty is flat, and so
        is a sensor's reading where it is clipped; a magnitude's turns with the sign of z."""
        L, limits, state = self.lag, self.start.output_limits, self.state
        outputs = []
        estimated, starts = self.started(theta)
        for (run, _), ya, into in zip(self.runs, starts, self.derivatives, strict=True):
            output, block = run.run_with_sensitivities(theta, ya, state, into)
            if estimated is not None:
                estimated.project(block[L:])
            if self.start.rectified:
                block *= np.sign(output)[:, None]
                output = np.abs(output)
            if limits is not None and state is None:
                low, high = limits
                block[(output <= low) | (output >= high)] = 0.0
                output = np.clip(output, low, high)
            outputs.append(output)
        return outputs

    def penalised(self, theta: np.ndarray, holding: bool) -> np.ndarray:
        outputs = self.sensitive(theta)
        residuals = self.errors(outputs)
        if (self.at_rest and not self.settles(theta, outputs)) or (
            holding and not self.ring_downs.holds(self.start, theta, self.start.theta)
        ):
            self.penalised_steps += 1
            return np.full(residuals.size, self.penalty)
        if not np.all(np.isfinite(residuals)):
            self.penalised_steps += 1
            return np.where(np.isfinite(residuals), residuals, self.penalty)
        return residuals

    # MINPACK is given the free-run error folded to p + 1 rows. Its steps depend on the residual r
    # and the Jacobian J only through ‖r‖, JᵀJ and Jᵀr (J's column norms among them), and the fold
    # keeps all three: at every θ the residual is ‖r‖·e₁, and at the points kept the Jacobian is
    # [R; 0] of J = QR with [Qᵀr; ρ], the rest of r, rotated onto e₁, so that
    # ‖‖r‖·e₁ + J̃p‖ = ‖r + Jp‖ for every step p. Given the tall J, MINPACK factors it unblocked,
    # half of Silverbox's output-error searches; blockwise (:func:`triangular_factor`) the factor
    # costs a third of that.

    def folded(self, theta: np.ndarray, holding: bool) -> np.ndarray:
        residuals = self.penalised(theta, holding)
        self.last.clear()
        self.last[theta.tobytes()] = residuals
        error = np.zeros(theta.size + 1)
        error[0] = np.linalg.norm(residuals)
        return error

    def jacobian(self, theta: np.ndarray, holding: bool) -> np.ndarray:
        if theta.tobytes() not in self.last:
            self.folded(theta, holding)
        residuals = self.last[theta.tobytes()]
        blocks = [into[self.lag :] for into in self.derivatives]
        # Columns scaled to a largest entry of one: sensitivities can exceed 10¹⁵⁴ where the run
        # stays finite (gauss_newton_inverse), and their squares must not overflow in the QR.
        # A NaN or an infinity (a diverging trial, rarely) is read as no sensitivity, as the
        # flat penalty is.
        scale = _column_scale(*blocks)
        if not np.isfinite(scale).all():
            blocks = [np.nan_to_num(block, nan=0.0, posinf=0.0, neginf=0.0) for block in blocks]
            scale = _column_scale(*blocks)
        for block, first, end in zip(blocks, self.rows[:-1], self.rows[1:], strict=True):
            np.divide(block, scale, out=self.augmented[first:end, :-1])
        self.augmented[:, -1] = residuals
        R = triangular_factor(self.augmented, threads=self.threads)
        triangle, along = R[:-1, :-1] * scale, R[:, -1]  # [Qᵀr; ±ρ]
        rotation, top = linalg.qr(along[:, None])  # along = rotation·(±‖r‖·e₁)
        rotation[:, 0] *= np.sign(top[0, 0]) or 1.0
        return rotation.T @ np.vstack([triangle, np.zeros((1, theta.size))])

    def run(self, max_evaluations: int, holding: bool) -> tuple[np.ndarray, Search, int]:
        """MINPACK's search from the start, within ``max_evaluations``; ``holding``, held to the
        restarts from measured outputs.

        MINPACK cuts its trust region tenfold on every step into the penalty and lets it grow at
        most twofold a step after, so a search that met the penalty can crawl to its step-size
        test (status 3) far from the optimum: on the rig with an unmeasured force, 32.5 mm of
        free-run RMS where 2.8 mm is reachable. A fresh search from where it stopped starts with
        a full region."""
        theta, evaluations = self.start.theta, 0
        while True:
            met_penalty = self.penalised_steps
            result = minimise(
                lambda at: self.folded(at, holding),
                lambda at: self.jacobian(at, holding),
                theta,
                max_evaluations - evaluations,
            )
            evaluations += int(result.nfev)
            theta = result.x
            if result.status != 3 or self.penalised_steps == met_penalty or evaluations >= max_evaluations:
                return theta, result, evaluations

    def outcome(
        self,
        theta: np.ndarray,
        result: Search,
        evaluations: int,
        initial: np.ndarray,
        holds: bool,
    ) -> OutputErrorFit:
        """The search's end ``theta`` as the fit, with its covariance; the start where the end
        does not run free lower than the start's ``initial`` error, or does not come to rest or
        hold where the start does."""
        start = self.start
        outputs = self.simulated(theta)
        final = self.errors(outputs)
        start_rms = float(np.sqrt(np.mean(initial**2)))
        if (
            not np.all(np.isfinite(final))
            or float(np.sqrt(np.mean(final**2))) >= start_rms
            or (self.at_rest and not self.settles(theta, outputs))
            or not holds
        ):
            return OutputErrorFit(start, start_rms, start_rms, evaluations, int(result.status))
        n, p = final.size, theta.size
        if self.start_from == "estimated":
            p += len(self.runs) * EstimatedStart.of(start.terms, theta, self.longest).responses.shape[1]
        sigma2 = float(final @ final) / max(n - p, 1)
        model = replace(
            start, theta=theta, covariance=sigma2 * gauss_newton_inverse(result.jac), sigma2=sigma2, n_obs=n
        )
        return OutputErrorFit(
            model, start_rms, float(np.sqrt(np.mean(final**2))), evaluations, int(result.status)
        )


def gauss_newton_inverse(jacobian: np.ndarray) -> np.ndarray:
    """(JᵀJ)⁺, the pseudo-inverse of the Gauss–Newton matrix of the Jacobian J (rows: the free
    run's samples; columns: θ), which times σ² is θ's asymptotic covariance.

    Computed on J's columns scaled to a largest entry of one, J = J_s·D, as D⁻¹(J_sᵀJ_s)⁺D⁻¹:
    the same matrix where JᵀJ is representable and of full rank, and a finite one where it is
    not. A free run's sensitivities can exceed 10¹⁵⁴ while the run itself stays finite, and JᵀJ
    then overflows (F-16's multisines, estimated whole: LAPACK's SVD failed on it in the middle
    of the loop; on other such matrices the pseudo-inverse comes back as zeros)."""
    scale = _column_scale(jacobian)
    scaled = jacobian / scale
    return np.linalg.pinv(scaled.T @ scaled) / scale[:, None] / scale[None, :]


def _column_scale(*blocks: np.ndarray) -> np.ndarray:
    """Each column's largest magnitude over the ``blocks`` (rows of one matrix; one for a column
    of zeros): dividing by it keeps the products of sensitivities that exceed 10¹⁵⁴ from
    overflowing. From the columns' largest and smallest entries, two passes with no copy of
    |J|; NaN where a column holds one."""
    high = np.max([block.max(axis=0, initial=0.0) for block in blocks], axis=0)
    low = np.min([block.min(axis=0, initial=0.0) for block in blocks], axis=0)
    scale = np.maximum(high, -low)
    scale[scale == 0.0] = 1.0
    return scale


# Where and for how long the excitation is switched off to see the free run come to rest: at this
# many points spread over the records, shared by their lengths (each record's end one of them),
# for this many samples. Shared, not per record: a record cut into blocks (the refinement's check
# split) would otherwise ring down eight times a block, more samples than the blocks themselves.
SWITCH_OFFS = 8
RING_DOWN = 1000
# Restarts from measured outputs, spread over the records likewise (RingDowns), each as long as a
# ring-down. A fragile model diverges from some measured states only: the F-16 sweeps' power-law
# model of acceleration 3 from 1.4, 9 and 15 % of them on levels 3, 5 and 7, within 13 samples
# of the restart at the median and 850 at most; eight restarts missed that, and 64 over the three
# records would miss it three times in a thousand.
RESTARTS = 64
# A ring-down that leaves this many times the records' largest measured output has not come to rest.
RESTLESS = 10.0
# A ring-down whose last samples lie within this share of that bound of each other has come to rest.
STILL = 1e-9
# The growth over the longest record beyond which a mode of the linearised model at rest drifts.
GROWTH = 2.0


def diverged(run: np.ndarray, measured: np.ndarray) -> bool:
    """Whether a free run ``run`` over a record whose measured output is ``measured`` has
    diverged: it is not finite, or it leaves ``RESTLESS`` times the largest measured output (a
    model growing without bound can stay finite over a record)."""
    return not np.all(np.isfinite(run)) or bool(np.max(np.abs(run)) > RESTLESS * np.max(np.abs(measured)))


@dataclass(frozen=True)
class RingDowns:
    """Free runs with the excitation switched off, and free runs restarted from measured outputs,
    prepared for a model's terms on its records.

    At ``SWITCH_OFFS`` points c over the records (a record's share of them by its length, at least
    its end) the free run's state ŷ[c−L … c−1] starts a run whose input is the record's up to c
    and zero after it, for ``RING_DOWN`` samples. At ``RESTARTS`` points spread so, a run starts
    from the *measured* outputs y[c−L … c−1] with the record's input, for as long: any validation
    starts a free run from measured outputs, and a model stable only along its own trajectory
    diverges there (F-16's multisine: a power-law model of acceleration 1 ran free over its
    estimation records from their first samples, rang down after every switch-off, and diverged
    within 15 samples of a test record's start, and from half the measured states of its own
    records). Such a restart must not diverge, unless the model's linear part rings from it beyond
    the bound below (:meth:`holds`). A model comes to rest when that holds and every ring-down

    - stays finite and within ``RESTLESS`` times the largest measured output: an unstable model's
      grows without bound, and a stable structure's free decay never beyond the state it starts
      from;
    - and ends still (its last samples within ``STILL`` of that bound of each other) or where the
      linearisation of the model's smooth part is stable: a slow mode stays within the bound over
      the ring-down and shows there only as a drift (the rig's structure grown by two lags, fitted by
      output error, has a root at 1.00056 and drifts to an equilibrium at 0.29 m, beyond the
      largest measured output, in 20 000 samples). The drift's root λ is judged by
      λ^N ≤ ``GROWTH`` over the N samples of the longest record: a growth the records would show.

    The linearisation is ŷ[t] ≈ Σ_k a_k ŷ[t−k] about the ring-down's last samples, with a_k the
    slopes of the polynomial terms in y and dy. Terms with an input factor vanish with the input,
    and so, to first order, do those whose other factors are absolute values or power laws of
    exponent one or more in a product of degree above one (dy·|dy|, |dy|^1.8·sign dy). A model
    with a term that has no slope at rest — a sign, an absolute value alone, a power law below
    one, a hysteresis variable (whose small motions follow y's), a sinusoid — is judged by its
    ring-downs' bound alone.
    """

    lag: int
    bound: float
    horizon: int  # samples of the longest record
    switch_offs: tuple[tuple[int, int], ...]  # (record, switch-off sample c)
    # The ring-downs' runs from c − L, one after the other as the rows of one, and the rows of each.
    decays: FreeRun | None
    decay_windows: np.ndarray
    # Each record's restarts: (the record's run, the rows (c − L, end) of each, the measured
    # y[c−L … c−1] of each), run together (:meth:`FreeRun.run_windows`).
    restarts: tuple[tuple[FreeRun, np.ndarray, np.ndarray], ...]
    linear: np.ndarray  # the terms of the model's linear part (plain lags of y, x, dy, dx), a mask on θ
    # Each polynomial autoregressive term: its index in θ and its factors as (lag, is a difference,
    # power); None when a term has no slope at rest and the model cannot be linearised there.
    smooth: tuple[tuple[int, tuple[tuple[int, bool, int], ...]], ...] | None

    @classmethod
    def build(
        cls,
        terms: Sequence[Term],
        records: Sequence[tuple[np.ndarray, np.ndarray]],
        origins: Sequence[int],
        driven: Sequence[FreeRun],
    ) -> RingDowns:
        """The ring-downs and restarts of ``terms`` on ``records`` (x, y), whose times start at
        ``origins``; ``driven`` are the records' free runs, whose rows the restarts are."""
        L = max_lag(terms)
        total = sum(len(y) for _, y in records)
        switch_offs, runs, restarts = [], [], []
        for index, ((x, y), origin, record_run) in enumerate(zip(records, origins, driven, strict=True)):
            if len(y) <= L:
                continue
            share = max(1, round(SWITCH_OFFS * len(y) / total))
            for c in np.unique(np.linspace(L, len(y), share + 1)[1:].astype(int)):
                unforced = np.concatenate([x[c - L : c], np.zeros(RING_DOWN)])
                switch_offs.append((index, int(c)))
                runs.append(FreeRun.build(terms, unforced, origin + int(c) - L))
            starts = max(1, round(RESTARTS * len(y) / total))
            points = np.unique(np.linspace(L, len(y), 2 * starts + 1)[1::2].astype(int))
            windows = np.column_stack([points - L, np.minimum(points + RING_DOWN, len(y))])
            measured = np.array([y[c - L : c] for c in points], dtype=float).reshape(points.size, L)
            restarts.append((record_run, windows, measured))
        edges = np.arange(len(runs) + 1) * (L + RING_DOWN)
        decay_windows = np.column_stack([edges[:-1], edges[1:]])
        decays = FreeRun.stacked(runs) if runs else None
        bound = RESTLESS * max((float(np.max(np.abs(y))) for _, y in records), default=0.0)
        at_rest = [_at_rest(term) for term in terms]
        smooth = (
            None
            if "none" in at_rest
            else tuple(
                (index, tuple((f.lag, f.signal == "dy", f.power) for f in term.factors))
                for index, (term, slope) in enumerate(zip(terms, at_rest, strict=True))
                if slope == "polynomial"
            )
        )
        horizon = max((len(y) for _, y in records), default=0)
        linear = np.array([_plain_lag(term) for term in terms], dtype=bool)
        return cls(
            L, bound, horizon, tuple(switch_offs), decays, decay_windows, tuple(restarts), linear, smooth
        )

    def settle(self, model: NARX, theta: np.ndarray, states: Sequence[np.ndarray]) -> bool:
        """Whether ``model`` with ``theta`` comes to rest after every switch-off, ``states`` being
        its recursion's free runs over the records with that θ (:func:`recursion_states`)."""
        if self.decays is None:
            return True
        limits = model.output_limits if model.saturation == "state" else None
        initial = [states[index][c - self.lag : c] for index, c in self.switch_offs]
        if not all(np.all(np.isfinite(state)) for state in initial):
            return False
        # Every ring-down run in one call; each must stay finite and bounded, and each that
        # ends moving must have a linearisation that does not drift.
        decays = self.decays.run_windows(theta, self.decay_windows, initial, limits)
        if not (np.all(np.isfinite(decays)) and float(np.max(np.abs(decays))) <= self.bound):
            return False
        if self.smooth is None:
            return True
        tails = decays[:, -self.lag - 1 :]
        moving = tails[np.ptp(tails, axis=1) > STILL * self.bound]
        # A smooth part of first-degree terms has the same linearisation at every state.
        if moving.size and all(len(f) == 1 and f[0][2] == 1 for _, f in self.smooth):
            moving = np.zeros((1, self.lag + 1))
        return not any(self.spectral_radius(theta, tail) > self.drifting for tail in moving)

    def holds(self, model: NARX, theta: np.ndarray, reference: np.ndarray) -> bool:
        """Whether ``model`` with ``theta`` does not diverge from any restart at measured outputs
        but those the linear part of ``model`` with ``reference`` rings from beyond the bound.

        Divergence, not a bound: a stable linear model with a lightly damped mode can ring far
        beyond the records' range from a noisy measured state and then decay (F-16's best linear
        models, held to ten times the largest measured output, simulated acceleration 3's test
        sweeps up to 31 % worse); a fragile polynomial model leaves every bound for good (each
        restart of the models below that left ten times the range diverged).

        Nor from a state the linear part (θ on the plain lags of y, x, dy and dx, the other terms
        at zero) rings from beyond the bound and back: there every other term is judged on
        outputs tens of times any measured, where no record says what it does. F-16's best linear
        model of acceleration 2 rings so from two of its 63 restarts (to 143 and 184 m/s², the
        sweeps reaching 7.4), and a cubic term of coefficient 10⁻⁸ beside it, which moves the
        free run by 0.03 %, diverges from those two and no other; fragile models diverge from
        measured states inside the range. A search passes its start's θ as ``reference``, so
        that it cannot earn itself exemptions by the linear parts it moves to.

        A sensor's clipped reading is not its recursion's state (:func:`recursion_states`): a
        sensor-saturating model is not restarted where the measured outputs reach its limits."""
        limits = model.output_limits if model.saturation == "state" else None
        clipped = model.output_limits if model.saturation == "sensor" else None
        linear_part = np.where(self.linear, reference, 0.0)
        for run, windows, measured in self.restarts:
            if clipped is not None:
                kept = ~np.any((measured <= clipped[0]) | (measured >= clipped[1]), axis=1)
                windows, measured = windows[kept], measured[kept]
            if not windows.size:
                continue
            # Every restart of a record in one call; NaN beyond a restart's end counts for nothing.
            out = run.run_windows(theta, windows, measured, limits)
            beyond = np.arange(out.shape[1]) >= (windows[:, 1] - windows[:, 0])[:, None]
            finite = np.all(np.isfinite(out) | beyond, axis=1)
            for w in np.flatnonzero(~finite):
                rung = run.run_windows(linear_part, windows[w : w + 1], measured[w : w + 1], limits)[0]
                if not (np.all(np.isfinite(rung)) and float(np.max(np.abs(rung))) > self.bound):
                    return False
        return True

    def rings(self, model: NARX, theta: np.ndarray) -> np.ndarray:
        """Of each restart at measured outputs, record after record, whether ``model`` with
        ``theta`` leaves the bound there or is not finite: ringing :meth:`holds` allows where it
        returns, which models of one structure are compared by restart for restart."""
        limits = model.output_limits if model.saturation == "state" else None
        rung = []
        for run, windows, measured in self.restarts:
            out = run.run_windows(theta, windows, measured, limits)
            beyond = np.arange(out.shape[1]) >= (windows[:, 1] - windows[:, 0])[:, None]
            peak = np.max(np.where(beyond, 0.0, np.abs(np.nan_to_num(out, nan=np.inf))), axis=1)
            rung.append(peak > self.bound)
        return np.concatenate(rung) if rung else np.zeros(0, dtype=bool)

    @property
    def drifting(self) -> float:
        """The smallest root that grows by ``GROWTH`` over the longest record."""
        return GROWTH ** (1.0 / self.horizon)

    def spectral_radius(self, theta: np.ndarray, tail: np.ndarray) -> float:
        """The largest root of z^R − Σ_k a_k z^(R−k), the smooth part linearised at ``tail`` (its
        last samples, the latest last; R = L + 1, so that dy[t−L] has its two samples)."""
        slopes = np.zeros(tail.size)  # a_1 … a_R
        for index, factors in self.smooth or ():
            values = [tail[-k] - tail[-k - 1] if difference else tail[-k] for k, difference, _ in factors]
            powered = [v**p for v, (_, _, p) in zip(values, factors, strict=True)]
            for i, (k, difference, power) in enumerate(factors):
                others = math.prod(powered[:i] + powered[i + 1 :])
                slope = theta[index] * others * power * values[i] ** (power - 1)
                slopes[k - 1] += slope
                if difference:
                    slopes[k] -= slope
        roots = np.roots(np.concatenate(([1.0], -slopes)))
        return float(np.max(np.abs(roots), initial=0.0))


def _plain_lag(term: Term) -> bool:
    """Whether a term is a plain lag of a signal, y[t-k], x[t-k], dy[t-k] or dx[t-k]."""
    if len(term.factors) != 1:
        return False
    (factor,) = term.factors
    return factor.power == 1 and factor.function == "" and factor.signal in ("y", "x", "dy", "dx")


def _at_rest(term: Term) -> Literal["polynomial", "vanishing", "none"]:
    """How a term's slope with respect to the output behaves at rest (:class:`RingDowns`)."""
    outputs = [f for f in term.factors if f.signal in ("y", "dy")]
    if not outputs or any(f.signal in ("x", "dx") for f in term.factors):
        return "vanishing"
    if len(outputs) < len(term.factors):  # a sinusoid of t
        return "none"
    if all(f.function == "" for f in outputs):
        return "polynomial"
    exponents = [f.parameter if f.function in ("spow", "apow") else 1.0 for f in outputs]
    smooth = all(f.function in ("", "abs", "spow", "apow") for f in outputs) and min(exponents) >= 1.0
    degree = sum(f.power * e for f, e in zip(outputs, exponents, strict=True))
    return "vanishing" if smooth and degree > 1.0 else "none"


def recursion_states(
    model: NARX, theta: np.ndarray, runs: Sequence[tuple[FreeRun, np.ndarray]], outputs: Sequence[np.ndarray]
) -> Sequence[np.ndarray]:
    """The recursion's own outputs over the records, given what ``model`` reports (``outputs``):
    the same but for a sensor's saturation, which clips only the reading — a ring-down started
    from clipped readings would start from a state the model was never in — or its magnitude."""
    if model.reads_state:
        return outputs
    return [run.run(theta, y) for run, y in runs]


def prepared(
    terms: Sequence[Term], records: Sequence[tuple[np.ndarray, np.ndarray]], origins: Sequence[int]
) -> tuple[list[FreeRun], RingDowns]:
    """Each record's free run of ``terms`` (:meth:`FreeRun.build`, times from its origin) and the
    ring-downs and restarts on them (:meth:`RingDowns.build`)."""
    runs = [FreeRun.build(terms, x, origin) for (x, _), origin in zip(records, origins, strict=True)]
    return runs, RingDowns.build(terms, records, origins, runs)


def comes_to_rest(
    model: NARX, records: Sequence[tuple[np.ndarray, np.ndarray]], t0: int | Sequence[int] = 0
) -> bool:
    """Whether ``model``'s free run over each of ``records`` (x, y) stays finite and rings down
    after the excitation is switched off anywhere in it, and its free run started from the
    measured outputs anywhere in it does not diverge (:class:`RingDowns`)."""
    return free_run_at_rest(model, records, t0)[1]


def free_run_at_rest(
    model: NARX, records: Sequence[tuple[np.ndarray, np.ndarray]], t0: int | Sequence[int] = 0
) -> tuple[float, bool]:
    """The free-run RMS of ``model`` over ``records`` (samples L … N−1 of each, infinite when a
    run diverges) and whether it comes to rest (:func:`comes_to_rest`), from one run a record."""
    origins = record_origins(t0, len(records))
    record_runs, ring_downs = prepared(model.terms, records, origins)
    runs = [(run, y) for run, (_, y) in zip(record_runs, records, strict=True)]
    outputs = [model.run_free(run, y) for run, y in runs]
    errors = np.concatenate(
        [out[model.max_lag :] - y[model.max_lag :] for out, (_, y) in zip(outputs, runs, strict=True)]
    )
    if not np.all(np.isfinite(errors)):
        return np.inf, False
    states = recursion_states(model, model.theta, runs, outputs)
    at_rest = ring_downs.holds(model, model.theta, model.theta) and ring_downs.settle(
        model, model.theta, states
    )
    return float(np.sqrt(np.mean(errors**2))), at_rest


def rings_from_measured(model: NARX, records: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Of each restart of ``model`` from the measured outputs on ``records`` (x, y), whether it
    leaves ``RESTLESS`` times their largest measured output (:meth:`RingDowns.rings`)."""
    _, ring_downs = prepared(model.terms, records, record_origins(0, len(records)))
    return ring_downs.rings(model, model.theta)


@dataclass(frozen=True)
class EstimatedStart:
    """The free run's start estimated from the whole record, for a model linear in its output.

    A free run started from the first L *measured* outputs starts from their noise, and for a
    structure sampled fast (a near-binomial autoregressive part, roots near one) the state those
    L noisy samples imply is far from the true one: its ring-down carries the noise amplified
    many times. An output-error fit then trades model error for a start that rings down quietly,
    and that trade is a bias that stays as the records grow and that is paid in proportion to
    the excitation (on a 3-DOF accelerometer at 1 kHz: the exact structure, 1 % sensor noise,
    a healthy simulation error a few percent above the noise, growing with the level squared).

    For a model whose autoregressive terms are plain lags of y, the free run is affine in its L
    initial outputs: ŷ(y₀ + c) = ŷ(y₀) + B·c, where column j of B (N × L) is the ring-down of the
    linear part from a unit on initial output j. The start minimising the error over the record,
    c = B⁺·(y − ŷ(y₀)), removes the start from the error: y − ŷ(y₀ + c) = P⊥·(y − ŷ(y₀)), with
    P⊥ the projection off B's columns (samples L … N−1). L of the record's degrees of freedom go
    to it. By the variable-projection theorem (Golub and Pereyra 1973), the gradient of
    ‖P⊥·(y − ŷ(θ; y₀))‖² over θ is that of the run from the estimated start at fixed c, so the
    search's Jacobian is −P⊥·∂ŷ(θ; y₀ + c)/∂θ (Kaufman's).
    """

    lag: int
    # B from row L on, (N_max − L, R): the last R initial outputs, R the longest lag of y (the
    # others do not reach the run).
    responses: np.ndarray

    @classmethod
    def of(cls, terms: Sequence[Term], theta: np.ndarray, n: int) -> EstimatedStart:
        """The start's responses of ``terms`` with ``theta`` over records of up to ``n`` samples;
        refused for a model whose autoregressive terms are not all plain lags of y."""
        L = max_lag(terms)
        a = np.zeros(L)
        for term, value in zip(terms, theta, strict=True):
            signals = {factor.signal for factor in term.factors}
            if not signals & {"y", "dy"}:
                continue
            (factor,) = term.factors if len(term.factors) == 1 else (None,)
            if factor is None or factor.signal != "y" or factor.power != 1 or factor.function != "":
                raise InputError(
                    f"the free run's start can be estimated only for a model linear in its output; "
                    f"{term.name} is not a plain lag of y"
                )
            a[factor.lag - 1] += value
        a = np.trim_zeros(a, "b")
        # Only the last R = len(a) initial outputs reach the run; one column for each.
        return cls(L, _start_responses(np.concatenate(([1.0], -a)), _unit_states(a), max(n - L, 0)))

    def start(self, y: np.ndarray, run_output: np.ndarray) -> np.ndarray:
        """The record's y with its first L samples replaced by the start that minimises the
        free-run error, given the run ``run_output`` started from the measured ones."""
        if not np.all(np.isfinite(run_output)):
            return y  # a diverging run is judged as it is, from the measured start
        B = self.responses[: y.size - self.lag]
        correction = np.linalg.lstsq(B, y[self.lag :] - run_output[self.lag :], rcond=None)[0]
        started = y.copy()
        started[self.lag - correction.size : self.lag] += correction
        return started

    def project(self, block: np.ndarray) -> None:
        """Project ``block``'s rows (samples L … N−1 of one record) off the start's responses,
        in place."""
        Q = np.linalg.qr(self.responses[: block.shape[0]])[0]
        block -= Q @ (Q.T @ block)


def _unit_states(a: np.ndarray) -> np.ndarray:
    """The filter states (R × R) from which 1/(1 − Σ a_i q⁻ⁱ) rings down from a unit on each of
    the last R initial outputs, column R−1−k that of a unit on y[L−1−k]: what
    ``signal.lfiltic([1.0], [1, −a…], e_k)`` computes one column at a time (zi[m] = a[m + k]),
    built at once, for a call of ``lfiltic`` costs more than the filtering at every θ of a search."""
    R = a.size
    states = np.zeros((R, R))
    for k in range(R):
        states[: R - k, R - 1 - k] = a[k:]
    return states


@numba.njit(cache=True, nogil=True)
def _start_responses(denominator: np.ndarray, states: np.ndarray, n: int) -> np.ndarray:
    """The (n, R) outputs of 1/denominator(q) on silence from each column of ``states``: what
    ``signal.lfilter([1.0], denominator, np.zeros(n), zi=column)`` gives, by its own arithmetic
    (the transposed direct form, the input's zero products kept), so bit for bit the same, but
    with the columns' independent recursions side by side, where lfilter runs one column after
    the other, each waiting on its own previous sample."""
    order, columns = states.shape
    out = np.empty((n, columns))
    z = states.copy()
    for t in range(n):
        for column in range(columns):
            y = z[0, column] + 1.0 * 0.0
            for m in range(order - 1):
                z[m, column] = z[m + 1, column] + 0.0 * 0.0 - y * denominator[m + 1]
            z[order - 1, column] = 0.0 * 0.0 - y * denominator[order]
            out[t, column] = y
    return out


def estimated_start_error(model: NARX, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y[t] − ŷ[t] of ``model``'s free run driven by x from the start estimated over the record
    (:class:`EstimatedStart`); zero over the first L samples, NaN from where a run diverges."""
    run = FreeRun.build(model.terms, x)
    started = EstimatedStart.of(model.terms, model.theta, y.size).start(y, model.run_free(run, y))
    error = y - model.run_free(run, started)
    error[: model.max_lag] = 0.0
    return error


# A pole and a zero whose pair moves the response by less than this share of it cancel: the pair
# (1 − z·q⁻¹)/(1 − p·q⁻¹) is one plus a filter whose impulse response has the norm
# |p − z|/√(1 − |p|²): the spurious pairs the accelerometer's searches ended in move it by orders
# of magnitude less than a hundredth, the slow poles that shape its response by an order more.
CANCELLED = 1e-2
# Only pairs whose pole rings for more than a few samples are taken out: a faster one's start
# column is not worth a second search.
SLOW = 0.5


def without_cancelled_poles(model: NARX) -> NARX | None:
    """``model`` with each slow pole that a zero cancels moved, with that zero, to the origin;
    None where it has none, or is not an ARX model (plain lags of y and of x, each lag from the
    first to the longest present).

    Fitted by output error from the estimated start (:class:`EstimatedStart`), such a pair leaves
    the free run driven by the input as it is and gives every record's start one more column to
    absorb the noise with, so the search can stop in it: the noisy accelerometer's baseline of
    ARX(5, 5) from ten short records ended with a pole at −0.98 and a zero within 10⁻⁴ of it, a
    start-up of 160 samples and more false alarms than its peers, where a lower error without the
    pair was to be had. At the origin the pair is a lag's coefficient of zero in each polynomial:
    the same response, one start column fewer, and a search from there is free to use the two
    coefficients for the response."""
    lags: dict[str, list[int]] = {"y": [], "x": []}
    for term in model.terms:
        (factor,) = term.factors if len(term.factors) == 1 else (None,)
        if factor is None or factor.signal not in lags or factor.power != 1 or factor.function != "":
            return None
        lags[factor.signal].append(factor.lag)
    if not lags["y"] or not lags["x"]:
        return None
    first_x = min(lags["x"])
    if sorted(lags["y"]) != list(range(1, max(lags["y"]) + 1)) or sorted(lags["x"]) != list(
        range(first_x, max(lags["x"]) + 1)
    ):
        return None
    a, b = np.zeros(len(lags["y"]) + 1), np.zeros(len(lags["x"]))  # 1 − Σ a_k z⁻ᵏ; b by lag from the first
    a[0] = 1.0
    for term, value in zip(model.terms, model.theta, strict=True):
        (factor,) = term.factors
        if factor.signal == "y":
            a[factor.lag] = -value
        else:
            b[factor.lag - first_x] = value
    if b[0] == 0.0:
        return None
    poles, zeros = np.roots(a), np.roots(b)
    free = np.ones(zeros.size, dtype=bool)
    cancelled = False
    for i in np.argsort(-np.abs(poles)):
        pole = poles[i]
        if abs(pole) <= SLOW or abs(pole) >= 1.0 or not free.any():
            continue
        j = int(np.argmin(np.where(free, np.abs(zeros - pole), np.inf)))
        if abs(zeros[j] - pole) / math.sqrt(1.0 - abs(pole) ** 2) < CANCELLED:
            poles[i], zeros[j], free[j], cancelled = 0.0, 0.0, False, True
    if not cancelled:
        return None
    a, b = np.poly(poles), b[0] * np.poly(zeros)
    if np.iscomplexobj(a) or np.iscomplexobj(b):
        return None  # a complex pole cancelled by a real zero, say: its conjugate was not
    theta = np.array(
        [
            -a[term.factors[0].lag] if term.factors[0].signal == "y" else b[term.factors[0].lag - first_x]
            for term in model.terms
        ]
    )
    return replace(model, theta=theta)
