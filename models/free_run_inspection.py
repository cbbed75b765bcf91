"""The inspection chain on the free-run (output) error, for structures whose noise is on the sensors.

The paper's chain (:mod:`models.inspection`) estimates the magnitude from the one-step residual
and localises by its whiteness: right when the noise enters the structure as a force, the
residual then being white. A sensor adds its noise to what it measures instead, and at a fast
sampling rate the one-step residual is then mostly that noise passed through the model's
autoregressive part, which nearly differences it: coloured whatever the mode, and nearly blind to
the magnitude (the lagged outputs it predicts from carry the change; :mod:`models.novelty`).
No Ljung–Box test can localise there, for no mode leaves a white residual. This chain works on
the free run's error from the start estimated over the record
(:class:`models.output_error.EstimatedStart`), which carries the fault's whole difference to
the response:

1. Fault modes whose free run is good: θ_V(k) = θ₀ + k·δ_V (p = 2, exact for a stiffness
   fault), one healthy θ₀ for every mode, fitted by output error jointly over all the modes'
   experiments (:func:`fit_free_run_modes`), from the equation-error fits (biased by the noisy
   lagged outputs) and from the terms' fits to a long ARX's free run, the lower end kept; an
   end whose healthy point has a slow pole its zero cancels is searched again without the pair,
   as :func:`models.output_error.fit_output_error` does, and an end without one is preferred. The
   healthy error level, the whitening filter w(q) (AR(Q) fitted to the experiments' errors, as
   in :mod:`models.novelty`) and σ̃²₀ (the whitened error's variance) come with them, and
   Cov vec(Θ_V) by the delete-one-experiment jackknife: with φ̂ = [θ₀; δ…] the joint fit and
   φ̂₍ᵢ₎ its refit without experiment i (from φ̂) of m,
   Cov φ̂ = (m − 1)/m·Σᵢ (φ̂₍ᵢ₎ − φ̄)(φ̂₍ᵢ₎ − φ̄)ᵀ, φ̄ the refits' mean, mapped to vec(Θ_V). Not
   σ̃²₀·(J̃ᵀJ̃)⁻¹, which takes the whitened error for the only difference between training sets:
   new training sets move φ̂ further than it allows, and the jackknife measures the spread
   between experiments whatever its source. Every mode needs experiments at three magnitudes or
   more.
2. k̂ = argmin_k Σ ε̃_k² over the mode's range, ε̃_k the whitened free-run error of θ(k) from
   the estimated start (a grid, then a bounded search around its best point).
3. σ̂_k by Gauss–Newton on the whitened error, so that the error's colour is accounted for
   (generalised least squares): d = ∂ŷ/∂k = S·Θ·g′(k̂), S the run's sensitivities to θ projected
   off the start's responses; σ̂²_k = s̃²/(d̃ᵀd̃), s̃² the record's whitened error variance; plus
   the delta-method term of the mode's own estimation error, ∇ᵀ·Cov vec(Θ)·∇ with
   ∇ = J̃_Θᵀd̃/(d̃ᵀd̃), J̃_Θ = S̃ ⊗ g(k̂), Cov vec(Θ) the jackknife's of step 1:
   σ̂²_k = c²·(σ̂²_k,record + σ̂²_k,mode), both parts in the verdict. c = 1 unless the mode's own
   experiments contradict it: each experiment i of the mode's m, inspected with the jackknife's
   refit without it, misses its known magnitude by z_i = (k̂_i − k_i)/σ̂_k,i, standard normal
   when σ̂_k is right; Σz²_i beyond χ²_m's 1 − HELD_OUT_LEVEL quantile makes c = √(Σz²_i/m).
   Both parts are linearisations at the fitted Θ, and both fail together where a mode's slope
   is mostly the fit's error: a far spring whose effect on the response is less than the healthy
   point's misfit, whose mode may then claim a slope many times the spring's, σ̂_k as many times
   too small, and healthy records far from k = 0.
4. Localisation: the candidate is the mode whose best k̂ leaves the smallest whitened error
   variance (maximum likelihood for Gaussian errors, as in the paper's chain); its adequacy is
   F = s̃²_V/σ̃²₀ ~ F(ν, ν₀) under the mode (ν = n − Q − R − 1 the record's whitened samples less
   the start's R columns and k̂, ν₀ the experiments' less Θ's), taken one-sided: a record the
   best mode describes worse than its experiments is an ``unknown_fault``.
5. Detection and the interval as in the paper's chain, Šidák's z and the adequacy test at a
   small share of α, but each mode's z is the signed root of the likelihood ratio against k = 0,
   (Σε̃²(0) − Σε̃²(k̂))/s̃², times σ̂_k,record/(c·σ̂_k) for the mode's own estimation error and
   its held-out scale: k̂/σ̂_k where the error is linear in k, and right where it is not. The
   interval is k̂ ± z_{1−α/2}·σ̂_k.
   The verdict is :class:`models.inspection.Verdict`; each mode's ``q``, ``q_critical``, ``p_value`` and
   ``accepted`` are the F test's (``lags`` is None: no Ljung–Box test is made), and
   ``whiteness`` in ``detected_by`` names the adequacy test.
6. What the record cannot determine is withheld, not guessed. Which mode: when another accepted
   mode's best fit is not worse than the best one's by the F test of its extra error,
   F = ν·(s̃²_V − s̃²_best)/s̃²_best ~ F(1, ν) at α, the fault is an ``unknown_fault`` (no mode,
   no magnitude; ``modes`` shows which are accepted). How much: when the localised mode's
   interval spans more than UNDETERMINED_SHARE of its range, the verdict names the mode but
   gives no ``k_hat``, ``sigma_k`` or ``interval`` (the mode's σ̂_k stays in ``modes``): a far
   spring the driving point barely feels.

For models linear in their output (the estimated start needs it) and without output limits.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy
from numpy.typing import ArrayLike
from scipy import special

from models.errors import InputError
from models.fnarx import FNARX, Experiment, fit_fnarx
from models.inspection import (
    ADEQUACY_SHARE,
    GRID_POINTS,
    ModeResult,
    Verdict,
    _check_finite,
    _decide,
    check_request,
)
from models.levenberg_marquardt import minimise
from models.narx import DOCUMENT_VERSION, check_document, z_quantile
from models.novelty import WHITENING_ORDER, _whitening_filter
from models.output_error import EstimatedStart, without_cancelled_poles
from models.signals import checked_record
from models.simulation import FreeRun
from models.terms import Term, max_degree, parse_terms

# Free runs a mode's joint output-error fit may compute, at most.
MAX_EVALUATIONS = 200
# The lags of the output and the input of the long ARX whose free run gives the joint fit its
# second start (:func:`_through_long_arx`): several times a structural model's, to take up the
# noise on the lagged outputs.
LONG_ARX_ORDER = 20
# The share of a mode's range beyond which an interval says the record does not determine the
# magnitude: wider than half the range, the interval hardly narrows what the mode's range says.
UNDETERMINED_SHARE = 0.5
# The level of the test of a mode against its held-out experiments (module docstring, step 3): a
# right mode's σ̂_k is scaled this seldom.
HELD_OUT_LEVEL = 0.01


@dataclass(frozen=True)
class FreeRunMode:
    """A fault-mode model fitted for its free run, with its healthy error level.

    Attributes
    ----------
    model : the FNARX, Θ fitted by output error; its covariance the jackknife's (module
        docstring, step 1).
    whitening : c_1 … c_Q of w(q) = 1 − Σ c_k q⁻ᵏ, fitted to the experiments' free-run errors.
    sigma2 : σ̃²₀, the experiments' whitened free-run error variance.
    dof : ν₀, the experiments' whitened samples less the start's columns and Θ's.
    scale : c ≥ 1, what σ̂_k is multiplied by: 1 unless the mode, refitted without each of its
        experiments, misses their magnitudes beyond what its σ̂_k allows (module docstring,
        step 3); documents written without it are read as 1.
    """

    model: FNARX
    whitening: np.ndarray
    sigma2: float
    dof: float
    scale: float = 1.0

    @property
    def name(self) -> str:
        return self.model.name

    def to_document(self) -> dict[str, Any]:
        """The FNARX's document with the healthy error level beside it."""
        return {
            "kind": "free_run_mode",
            "schema_version": DOCUMENT_VERSION,
            "model": self.model.to_document(),
            "whitening": self.whitening.tolist(),
            "sigma2": self.sigma2,
            "dof": self.dof,
            "scale": self.scale,
        }

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> FreeRunMode:
        check_document(document, "free_run_mode")
        try:
            mode = cls(
                FNARX.from_document(document["model"]),
                np.asarray(document["whitening"], dtype=np.float64),
                float(document["sigma2"]),
                float(document["dof"]),
                float(document.get("scale", 1.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"free-run fault-mode document: missing or invalid field ({exc})") from None
        if mode.whitening.ndim != 1 or not (mode.sigma2 > 0 and mode.dof > 0 and 1 <= mode.scale < np.inf):
            raise InputError("free-run fault-mode document: whitening, sigma2, dof or scale out of range")
        return mode


@dataclass(frozen=True)
class _Run:
    """One record's free run of a mode at one magnitude, from the estimated start: the error
    (samples L … N−1) and, when asked for, the run's sensitivities to θ projected off the start's
    responses."""

    error: np.ndarray
    sensitivities: np.ndarray | None
    start_columns: int


def _free_run(terms: Sequence[Term], run: FreeRun, theta: np.ndarray, y: np.ndarray, sensitive: bool) -> _Run:
    L = run.lag
    start = EstimatedStart.of(terms, theta, y.size)
    started = start.start(y, run.run(theta, y))
    if not sensitive:
        return _Run(y[L:] - run.run(theta, started)[L:], None, start.responses.shape[1])
    output, S = run.run_with_sensitivities(theta, started)
    S = S[L:]
    if np.all(np.isfinite(S)):
        start.project(S)
    return _Run(y[L:] - output[L:], S, start.responses.shape[1])


def _whitened(whitening: np.ndarray, series: np.ndarray) -> np.ndarray:
    """``series`` (along its first axis) through w(q), its first Q samples dropped."""
    return scipy.signal.lfilter(np.concatenate(([1.0], -whitening)), [1.0], series, axis=0)[whitening.size :]


def fit_free_run_modes(
    experiments: Mapping[str, Iterable[Experiment]],
    terms: Sequence[str | Term],
    *,
    max_evaluations: int = MAX_EVALUATIONS,
) -> list[FreeRunMode]:
    """Fault modes, one for each name's experiments (x, y, k), whose free runs are good: the
    modes are fitted jointly, θ_V(k) = θ₀ + k·δ_V with one healthy θ₀ for all, minimising the
    free-run error from the estimated start summed over every experiment; module docstring,
    step 1. From the paper's equation-error fits (:func:`models.fnarx.fit_fnarx`, p = 2, each
    mode's range its experiments') and from the fits to a long ARX's free run
    (:func:`_through_long_arx`), the search's lower end kept: the free-run error is not convex
    in θ, and from the biased equation-error point alone the search may end in a basin whose
    healthy point misses the response by more than a far spring's fault changes it.

    One θ₀: fitted apart, each mode's healthy point carries its own experiments' estimation
    error, and the modes' errors on one record then differ by more than a far spring's fault
    does (the localisation compares them), and a mode's k̂ absorbs its healthy point's error.
    Θ's covariance is the delete-one-experiment jackknife's, a refit for every experiment.
    """
    runs = {name: list(experiments[name]) for name in experiments}
    for name, own in runs.items():
        if len({float(k) for _, _, k in own}) < 3:
            raise InputError(
                f"fault mode {name!r} needs experiments at three magnitudes or more: its estimation "
                "error is measured by refitting without each one, and two points leave no line to refit"
            )
    starts = [fit_fnarx(own, terms, name=name) for name, own in runs.items()]
    joint = _Joint.of(runs, starts[0].terms, starts[0].max_lag, max_evaluations)
    through_long = [_through_long_arx(own, joint.terms, name) for name, own in runs.items()]
    flat = joint.searched(starts, through_long)
    fitted = joint.evaluate(flat, True)
    if not all(np.all(np.isfinite(run.error)) for run in fitted):
        raise InputError("the output-error fit of the fault modes diverges on their experiments")
    whitening, sigma2, dof = _error_level(fitted, flat.size)
    refits, covariance = joint.jackknife(flat)
    modes = []
    for index, start in enumerate(starts):
        T = _to_mode(start, index, flat.size)
        own = [run for run, owner in zip(fitted, joint.owners, strict=True) if owner == index]
        model = replace(
            start,
            theta=(T @ flat).reshape(-1, 2),
            covariance=T @ covariance @ T.T,
            experiment_sigma2=np.array([float(np.mean(run.error**2)) for run in own]),
        )
        mode = FreeRunMode(model, whitening, sigma2, dof)
        held_out = [
            (
                replace(model, theta=(T @ refits[i]).reshape(-1, 2)),
                joint.runs[i],
                joint.records[i],
                joint.magnitudes[i],
            )
            for i in joint.everything
            if joint.owners[i] == index
        ]
        modes.append(replace(mode, scale=_held_out_scale(mode, held_out)))
    return modes


@dataclass
class _Joint:
    """The modes' joint output-error problem over all their experiments: φ = [θ₀; δ_1; …; δ_M],
    experiment i's θ = maps[i]·φ (θ₀ + k_i·δ of its owner's mode)."""

    terms: Sequence[Term]
    records: list[np.ndarray]
    runs: list[FreeRun]
    maps: list[np.ndarray]
    owners: list[int]
    magnitudes: list[float]
    max_evaluations: int
    scale: float = 1.0  # the error a diverging trial is given, per sample (:meth:`fit`)

    @classmethod
    def of(
        cls,
        runs: Mapping[str, Sequence[Experiment]],
        terms: Sequence[Term],
        max_lag: int,
        max_evaluations: int,
    ) -> _Joint:
        n = len(terms)
        records, free, maps, owners, magnitudes = [], [], [], [], []
        for index, own in enumerate(runs.values()):
            for x, y, k in own:
                xa, ya = checked_record(x, y, max_lag + n + 1, degree=max_degree(terms))
                records.append(ya)
                owners.append(index)
                magnitudes.append(float(k))
                free.append(FreeRun.build(terms, xa))
                maps.append(
                    np.hstack([np.eye(n)] + [float(k) * np.eye(n) * (j == index) for j in range(len(runs))])
                )
        return cls(terms, records, free, maps, owners, magnitudes, max_evaluations)

    @property
    def everything(self) -> range:
        return range(len(self.records))

    def evaluate(self, flat: np.ndarray, sensitive: bool, kept: Iterable[int] | None = None) -> list[_Run]:
        kept = self.everything if kept is None else kept
        return [
            _free_run(self.terms, self.runs[i], self.maps[i] @ flat, self.records[i], sensitive) for i in kept
        ]

    def fit(self, initial: np.ndarray, kept: Sequence[int]) -> np.ndarray:
        """φ minimising the free-run error over experiments ``kept``, searched from ``initial``."""

        def residuals(flat: np.ndarray) -> np.ndarray:
            error = np.concatenate([-run.error for run in self.evaluate(flat, False, kept)])
            # A diverging trial is backed away from.
            return np.where(np.isfinite(error), error, 1e6 * self.scale)

        def jacobian(flat: np.ndarray) -> np.ndarray:
            runs = self.evaluate(flat, True, kept)
            return np.nan_to_num(
                np.vstack([run.sensitivities @ self.maps[i] for run, i in zip(runs, kept, strict=True)])
            )

        # MINPACK's search, as least_squares(method="lm", x_scale="jac") runs it, without its read
        # past the Jacobian (models.levenberg_marquardt).
        return minimise(residuals, jacobian, initial, self.max_evaluations).x

    def searched(self, starts: Sequence[FNARX], through_long: Sequence[FNARX | None]) -> np.ndarray:
        """The joint fit: the search from each start whose free run stays finite on every
        experiment, and from each end whose healthy point has a slow pole its zero cancels again
        with the pair taken out (:func:`models.output_error.without_cancelled_poles`); the lowest
        end without such a pair kept, the lowest of all where every end has one. Sets
        :attr:`scale` from the first start's error.

        A cancelled pair leaves the free run driven by the input as it is, and gives each
        experiment's start a column to absorb the noise with: its lower error is the noise's. The
        accelerometer chain's ARX(4, 4) ended so in some training sets, a pole near −0.93 and its
        zero, the chain's response left to three poles: its healthy point then missed the
        response by several times what the far spring's loosening changes, and the far spring's
        mode spent its slope on that misfit."""
        initials = [_joined(starts)] + (
            [_joined(through_long)] if all(start is not None for start in through_long) else []
        )
        initials = [
            flat
            for flat in initials
            if all(np.all(np.isfinite(run.error)) for run in self.evaluate(flat, False))
        ]
        if not initials:
            raise InputError(
                "the equation-error fit of the fault modes diverges in free run on their experiments: "
                "choose a lower order"
            )
        first = np.concatenate([run.error for run in self.evaluate(initials[0], False)])
        self.scale = float(np.sqrt(np.mean(first**2))) or 1.0
        everything = list(self.everything)
        ends = [self.fit(flat, everything) for flat in initials]
        untangled = [self._untangled(starts[0], end) for end in ends]
        for flat in [flat for flat in untangled if flat is not None]:
            ends.append(self.fit(flat, everything))
            untangled.append(self._untangled(starts[0], ends[-1]))
        sums = [_sum_of_squares(self.evaluate(end, False)) for end in ends]
        finite = [i for i, total in enumerate(sums) if np.isfinite(total)] or list(range(len(ends)))
        clean = [i for i in finite if untangled[i] is None]
        return ends[min(clean or finite, key=sums.__getitem__)]

    def _untangled(self, start: FNARX, flat: np.ndarray) -> np.ndarray | None:
        """``flat`` with its healthy point's cancelled pairs taken out, None where it has none.
        Each slope then joins it to the mode's point at its largest magnitude, taken out alike
        (zero where that point has no such pair): the slope fitted with the pair holds the
        pair's coefficients too, and added to the healthy point without it may run unstable."""
        n = len(self.terms)
        healthy = without_cancelled_poles(replace(start.narx_at(0.0), theta=flat[:n]))
        if healthy is None:
            return None
        slopes = []
        for index in range(len(flat) // n - 1):
            k = max(k for k, owner in zip(self.magnitudes, self.owners, strict=True) if owner == index)
            far = without_cancelled_poles(
                replace(healthy, theta=flat[:n] + k * flat[n * (index + 1) : n * (index + 2)])
            )
            slopes.append(np.zeros(n) if far is None else (far.theta - healthy.theta) / k)
        return np.concatenate([healthy.theta, *slopes])

    def jackknife(self, flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The delete-one-experiment jackknife (module docstring, step 1): the refits of φ̂ without
        each experiment, each from the joint fit ``flat``, and Cov φ̂."""
        refits = np.array([self.fit(flat, [j for j in self.everything if j != i]) for i in self.everything])
        deviations = refits - refits.mean(axis=0)
        return refits, (len(refits) - 1) / len(refits) * (deviations.T @ deviations)


def _error_level(fitted: Sequence[_Run], size: int) -> tuple[np.ndarray, float, float]:
    """w(q), σ̃²₀ and ν₀ of the joint fit's errors on the experiments, φ of ``size``."""
    whitening = _whitening_filter([run.error for run in fitted], WHITENING_ORDER)
    errors = [_whitened(whitening, run.error) for run in fitted]
    dof = float(sum(e.size for e in errors) - sum(run.start_columns for run in fitted) - size)
    return whitening, float(sum(float(e @ e) for e in errors)) / dof, dof


def _to_mode(start: FNARX, index: int, size: int) -> np.ndarray:
    """T with vec(Θ_V) = T·φ for mode ``index`` (term i, basis j): Θ_V·[g(k_min) g(k_max)] =
    [θ_V(k_min) θ_V(k_max)], θ_V(end) = θ₀ + end·δ_V."""
    n = len(start.terms)
    ends = np.array([start.basis.k_min, start.basis.k_max])
    inverse = np.linalg.inv(start.basis.values(ends).T)  # row j: G_j's weights of the two ends
    at_ends = [np.hstack([np.eye(n), end * np.eye(n)]) for end in ends]  # θ₀, δ_V ↦ θ_V(end)
    T = np.zeros((2 * n, size))
    selected = np.r_[0:n, n * (index + 1) : n * (index + 2)]
    for j in range(2):
        T[j::2, selected] = sum(inverse[e, j] * at_ends[e] for e in range(2))
    return T


def _held_out_scale(mode: FreeRunMode, held_out: Sequence[tuple[FNARX, FreeRun, np.ndarray, float]]) -> float:
    """c of ``mode`` (module docstring, step 3) from its experiments, each inspected with the
    mode refitted without it: (model, run, y, k) of each.

    Each held-out miss z_i = (k̂_i − k_i)/σ̂_k,i is standard normal when σ̂_k is right, the
    experiment not being in the refit; Σz²_i beyond χ²_m's (1 − HELD_OUT_LEVEL) quantile says
    the mode's slope is not what its experiments show (a far spring's mode that took up the healthy
    point's misfit), and σ̂_k is then scaled by c = √(Σz²_i/m), what the misses say it is.
    """
    estimates = [(_estimate(replace(mode, model=model), run, y, True), k) for model, run, y, k in held_out]
    misses = [(estimate.k_hat - k) / estimate.sigma_k for estimate, k in estimates]
    total = float(np.sum(np.square(misses)))
    if total <= float(scipy.stats.chi2.ppf(1 - HELD_OUT_LEVEL, len(misses))):
        return 1.0
    return float(np.sqrt(total / len(misses)))


def _joined(starts: Sequence[FNARX]) -> np.ndarray:
    """[θ₀; δ_1; …; δ_M] of the joint fit from one start a mode: the modes' mean healthy point
    and each one's slope there."""
    return np.concatenate(
        [np.mean([start.coefficients(0.0) for start in starts], axis=0)]
        + [start.theta @ start.basis.derivatives(0.0) for start in starts]
    )


def _sum_of_squares(runs: Sequence[_Run]) -> float:
    value = float(sum(float(run.error @ run.error) for run in runs))
    return value if np.isfinite(value) else np.inf


def _through_long_arx(runs: Sequence[Experiment], terms: Sequence[Term], name: str) -> FNARX | None:
    """The equation-error fit of ``terms`` to the free runs of a long ARX fitted to the same
    experiments (``terms`` and the output's and input's lags up to LONG_ARX_ORDER): a second
    start for the joint output-error search, None where the long ARX's free run diverges.

    The terms' own equation-error fit regresses on noisy lagged outputs, and from its biased
    point the search may settle in another basin than the free run's best: on the accelerometer
    chain it kept a spurious negative pole (ringing at half the sampling rate) in place of the
    slow one, and its healthy free run strayed from the chain's response by several times what
    the far spring's loosening changes. The long ARX's free run carries no noise, so the terms'
    fit to it has no noisy regressors: a start biased otherwise, from which the search on that
    chain found the slow pole.
    """
    lags = [f"y[t-{i}]" for i in range(1, LONG_ARX_ORDER + 1)] + ["x[t]"]
    lags += [f"x[t-{i}]" for i in range(1, LONG_ARX_ORDER + 1)]
    long = fit_fnarx(runs, list(terms) + [term for term in parse_terms(lags) if term not in terms], name=name)
    simulated = []
    for x, y, k in runs:
        xa, ya = checked_record(x, y, long.max_lag + 1, degree=max_degree(long.terms))
        free = FreeRun.build(long.terms, xa).run(long.coefficients(float(k)), ya)
        if not np.all(np.isfinite(free)):
            return None
        simulated.append((xa, free, k))
    return fit_fnarx(simulated, terms, name=name, k_range=(long.basis.k_min, long.basis.k_max))


@dataclass(frozen=True)
class _Estimate:
    k_hat: float
    sigma_k: float
    sigma_k_record: float
    z: float  # the detection statistic
    sigma2: float  # s̃², the whitened error variance
    dof: float
    at_range_limit: bool


def _estimate(mode: FreeRunMode, run: FreeRun, y: np.ndarray, model_uncertainty: bool) -> _Estimate:
    model, basis = mode.model, mode.model.basis

    # Cached: the search ends by comparing its point with the grid's best, and the likelihood
    # ratio asks for k = 0, both magnitudes whose cost the grid may already have.
    @functools.cache
    def cost(k: float) -> float:  # the whitened error's sum of squares (generalised least squares)
        error = _whitened(
            mode.whitening, _free_run(model.terms, run, model.theta @ basis.values(k), y, False).error
        )
        value = float(error @ error)
        return value if np.isfinite(value) else np.inf

    grid = np.linspace(basis.k_min, basis.k_max, GRID_POINTS)
    best = int(np.argmin([cost(k) for k in grid]))
    low, high = grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)]
    found = scipy.optimize.minimize_scalar(
        cost, bounds=(low, high), method="bounded", options={"xatol": 1e-6}
    )
    k_hat = float(found.x) if found.fun <= cost(grid[best]) else float(grid[best])
    at = _free_run(model.terms, run, model.theta @ basis.values(k_hat), y, True)
    if not np.all(np.isfinite(at.error)):
        raise InputError(
            f"the free run of fault mode {model.name!r} diverges on the record at every magnitude tried"
        )
    error = _whitened(mode.whitening, at.error)
    S = _whitened(mode.whitening, at.sensitivities)
    slope = S @ (model.theta @ basis.derivatives(k_hat))  # ∂ŷ/∂k, whitened
    information = float(slope @ slope)
    if not information > 0:
        raise InputError(
            f"the record carries no information on the magnitude of fault mode {model.name!r}: "
            "the free run does not depend on k (is the excitation zero?)"
        )
    dof = float(error.size - at.start_columns - 1)
    sigma2 = float(error @ error) / dof
    variance_record = sigma2 / information
    variance = variance_record
    if model_uncertainty:
        gradient = np.kron(S.T @ slope, basis.values(k_hat)) / information
        variance += float(gradient @ model.covariance @ gradient)
    sigma_k, sigma_k_record = (
        mode.scale * float(np.sqrt(variance)),
        mode.scale * float(np.sqrt(variance_record)),
    )
    # The likelihood ratio of k̂ against the healthy k = 0, as a signed z: k̂/σ̂_k where the error is
    # linear in k over the interval, and right where it is not (a far spring's σ̂_k spans the
    # mode's range, and k̂ is then pushed against its ends far more often than k̂/σ̂_k says).
    # Scaled by σ̂_k,record/σ̂_k for the mode's own estimation error, which the ratio leaves out,
    # and by 1/c for a mode its held-out experiments contradict.
    if basis.contains(0.0):
        drop = max(cost(0.0) - float(error @ error), 0.0)
        z = float(np.sign(k_hat) * np.sqrt(drop / sigma2)) * sigma_k_record / sigma_k / mode.scale
    else:
        z = k_hat / sigma_k
    span = basis.k_max - basis.k_min
    limit = min(k_hat - basis.k_min, basis.k_max - k_hat) < 1e-6 * span
    return _Estimate(k_hat, sigma_k, sigma_k_record, z, sigma2, dof, limit)


def checked_for_free_run(
    x: ArrayLike, y: ArrayLike, fault_modes: Sequence[FreeRunMode]
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) as float64 vectors fit to be inspected with ``fault_modes``: long enough for the
    whitened free-run error after the modes' longest lag, and within the terms' magnitude limit.
    A service that queues an inspection checks a record with this before storing it, so that the
    queued inspection cannot fail on what the upload could have refused."""
    longest = max(mode.model.max_lag for mode in fault_modes)
    degree = max_degree([term for mode in fault_modes for term in mode.model.terms])
    return checked_record(x, y, longest + WHITENING_ORDER + 100, degree=degree)


def inspect_free_run(
    x: ArrayLike,
    y: ArrayLike,
    fault_modes: Sequence[FreeRunMode],
    *,
    alpha: float = 0.05,
    adequacy_share: float = ADEQUACY_SHARE,
    model_uncertainty: bool = True,
) -> Verdict:
    """Run the free-run chain on one record (x: excitation, y: response); module docstring."""
    check_request([mode.name for mode in fault_modes], alpha, adequacy_share)
    xa, ya = checked_for_free_run(x, y, fault_modes)
    adequacy_alpha = adequacy_share * alpha
    magnitude_level = 1 - ((1 - alpha) / (1 - adequacy_alpha)) ** (1 / len(fault_modes))
    z_detect = z_quantile(1 - magnitude_level)
    results, dofs = [], []
    for mode in fault_modes:
        estimate = _estimate(mode, FreeRun.build(mode.model.terms, xa), ya, model_uncertainty)
        ratio = estimate.sigma2 / mode.sigma2
        critical = float(special.fdtri(estimate.dof, mode.dof, 1 - alpha))
        dofs.append((estimate.dof, mode.dof))
        z = estimate.z
        results.append(
            ModeResult(
                name=mode.name,
                k_hat=estimate.k_hat,
                sigma_k=estimate.sigma_k,
                sigma_k_record=estimate.sigma_k_record,
                z=z,
                detects=bool(abs(z) > z_detect),
                residual_variance=estimate.sigma2,
                q=ratio,
                q_critical=critical,
                p_value=float(special.fdtrc(estimate.dof, mode.dof, ratio)),
                accepted=bool(ratio <= critical),
                at_range_limit=estimate.at_range_limit,
            )
        )
    _check_finite(results)
    # The adequacy test that detects is the best mode's at its share of α.
    best = int(np.argmin([result.residual_variance for result in results]))
    f_detect = float(special.fdtri(*dofs[best], 1 - adequacy_alpha))
    verdict = replace(_decide(results, alpha, 0, ya.size, z_detect, f_detect), lags=None)
    return _withheld(verdict, fault_modes, dofs[best][0])


def _withheld(verdict: Verdict, fault_modes: Sequence[FreeRunMode], dof: float) -> Verdict:
    """The verdict without what the record cannot determine (module docstring, step 6).

    Which mode: another accepted mode's best fit that the F test of its extra error,
    F = ν·(s̃²_V − s̃²_best)/s̃²_best ~ F(1, ν), cannot tell from the best one makes the fault an
    ``unknown_fault``: a fault of one of those modes, the record not saying which. How much: a
    localised mode whose interval spans more than UNDETERMINED_SHARE of its range keeps its name
    but gives no magnitude (``k_hat``, ``sigma_k`` and ``interval`` None); its σ̂_k stays in
    ``modes``.
    """
    if verdict.status != "faulty":
        return verdict
    best = verdict.mode(verdict.fault_mode)
    critical = float(special.fdtri(1.0, dof, 1 - verdict.alpha))
    if any(
        mode.accepted
        and dof * (mode.residual_variance - best.residual_variance) / best.residual_variance <= critical
        for mode in verdict.modes
        if mode is not best
    ):
        return replace(
            verdict,
            status="unknown_fault",
            fault_mode=None,
            reference_mode=None,
            k_hat=None,
            sigma_k=None,
            interval=None,
        )
    basis = next(mode.model.basis for mode in fault_modes if mode.name == best.name)
    low, high = verdict.interval
    if high - low > UNDETERMINED_SHARE * (basis.k_max - basis.k_min):
        return replace(verdict, k_hat=None, sigma_k=None, interval=None)
    return verdict
