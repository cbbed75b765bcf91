"""NARMAX models: NARX process terms plus moving-average noise terms.

When the equation error is coloured,

    y[t] = φ[t]ᵀθ + Σ_{i=1..q} c_i·e[t−i] + e[t],    e white,

its past values are correlated with the lagged outputs in φ[t], and ordinary least squares on
the process terms alone is biased. Extended least squares (Billings & Voon's NARMAX
estimation, Ljung's pseudo-linear regression) replaces the unknown e by residuals:

1. ε⁽⁰⁾ = y − Φθ̂⁽⁰⁾, the least-squares residual of the process terms;
2. β̂⁽ⁱ⁾ = [θ̂; ĉ] by least squares on [Φ | E(ε⁽ⁱ⁻¹⁾)], E holding ε[t−1] … ε[t−q];
3. ε⁽ⁱ⁾ = ½·(ε⁽ⁱ⁻¹⁾ + y − [Φ | E(ε⁽ⁱ⁻¹⁾)]·β̂⁽ⁱ⁾),

until every parameter moves by less than ``rtol`` standard errors. Step 3 is relaxed: it has
the same fixed point as feeding the new residual back unchanged, which on some records
oscillates about it for ever. Each record keeps its own residual series, pre-windowed (ε = 0
before its first equation), so no lag crosses records. The covariance is that of the last
least-squares fit, which treats the residual regressors as known: it understates the spread of
θ̂ somewhat (by ~25 % in the tests' Monte Carlo).

The pseudo-linear regression is sure to converge only where 1/C − 1/2 is positive real
(Ljung, *System Identification*, 1999). On a colour with a root near the unit circle, such as
the simulator's force-sensor noise C(z) = 1 + 1.5z⁻¹ + 1.2z⁻² + 0.9z⁻³ + 0.6z⁻⁴ + 0.3z⁻⁵ (a
root at 0.91), it does not settle: it wanders far from the coefficients, the lagged output's
coefficient biased with them, and its estimates at the cap are wherever the cap stopped it
(``converged`` False). The one-step prediction error's minimum is reached from there by
:func:`prediction_error`: the innovations

    ξ = (y − Φθ) / C(q),    C(q) = 1 + Σ c_i q⁻ⁱ,

each record's from rest, minimise Σξ² over θ and c together by Gauss–Newton (∂ξ/∂θ = −Φ/C(q),
∂ξ/∂c_i = −q⁻ⁱξ/C(q)), each step shortened until the sum falls, C kept invertible
(:func:`invertible`), until no parameter moves by ``rtol`` standard errors; the covariance is
σ̂²(JᵀJ)⁻¹ at the estimates, J the Jacobian of ξ. Where the model is right the two estimators
have one limit, the true parameters; where it is not they estimate different things, and the
loop's rounds keep extended least squares (docs/benchmarks/planted.md, "Extended least squares
that does not settle"). A moving average of a residual alone, the noise model's
(:mod:`models.noise_model`), is fitted by the same search from Hannan and Rissanen's estimate
(:func:`moving_average`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import scipy
from numpy.typing import ArrayLike
from scipy import linalg

from models.errors import InputError
from models.narx import NARX
from models.regression import checked_condition, scaled_covariance, scaled_qr
from models.signals import checked_records
from models.terms import Term, max_degree, max_lag, parse_terms, stacked_regressors

# A step of the prediction-error search is halved until the sum of squares falls, down to this
# fraction of Gauss–Newton's step; below it the search is at a minimum to the arithmetic's
# precision or stuck, and stops.
MIN_STEP = 1e-3
# Hannan and Rissanen's long autoregression, in multiples of the moving-average order.
LONG_AR_FACTOR = 4


@dataclass(frozen=True)
class NARMAX:
    """Process model and moving-average noise model estimated together.

    Attributes
    ----------
    process : the NARX part: terms, θ̂ and its covariance block, σ̂² = mean(ε²).
    noise : MA coefficients c_1 … c_q.
    noise_covariance : covariance of ĉ.
    iterations : least-squares fits after the initial one.
    converged : whether the last iteration moved every parameter by less than ``rtol`` s.e.; where
        it did not, the estimates are wherever the cap stopped the iteration.
    """

    process: NARX
    noise: np.ndarray
    noise_covariance: np.ndarray
    iterations: int
    converged: bool

    @property
    def noise_lags(self) -> int:
        return self.noise.size


def fit_narmax(
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    terms: Sequence[str | Term],
    noise_lags: int,
    *,
    max_iter: int = 100,
    rtol: float = 1e-2,
    t0: int | Sequence[int] = 0,
) -> NARMAX:
    """Estimate a NARMAX model by extended least squares (module docstring); ``t0`` as for
    :func:`models.narx.fit_narx`."""
    if isinstance(noise_lags, bool) or not isinstance(noise_lags, int) or noise_lags < 1:
        raise InputError(f"noise_lags must be an integer >= 1, got {noise_lags!r}")
    if max_iter < 1:
        raise InputError(f"max_iter must be >= 1, got {max_iter}")
    parsed = parse_terms(terms)
    L = max_lag(parsed)
    n_par = len(parsed) + noise_lags
    checked = checked_records(records, L + n_par + 1, degree=max_degree(parsed))
    Phi, target, starts = stacked_regressors(parsed, checked, L, t0)
    names = [term.name for term in parsed] + [f"e[t-{i}]" for i in range(1, noise_lags + 1)]
    step, iterations, converged = _extended_least_squares(
        Phi, target, starts, noise_lags, names, max_iter, rtol
    )
    # The last step is the least-squares fit on [Φ | E] with E the residual columns it was given.
    k = len(parsed)
    theta, covariance = step.theta, step.covariance
    process = NARX(parsed, theta[:k], covariance[:k, :k], step.sigma2, target.size)
    return NARMAX(process, theta[k:], covariance[k:, k:], iterations, converged)


def _extended_least_squares(
    Phi: np.ndarray,
    target: np.ndarray,
    starts: np.ndarray,
    noise_lags: int,
    names: Sequence[str],
    max_iter: int,
    rtol: float,
) -> tuple[_Step, int, bool]:
    """The relaxed extended least-squares iteration (module docstring): its last least-squares
    fit, the fits made after the first, and whether the last moved every parameter by less than
    ``rtol`` standard errors."""
    # Φ stays fixed while the residual columns change: its QR is computed once (which also refuses
    # a degenerate design), and each iteration solves for the q new columns through the Schur
    # complement of Φ's block (a block QR update without forming E's orthogonal part).
    Q1, R1, process_scale, _ = scaled_qr(Phi, names[: Phi.shape[1]])
    projected = Q1.T @ target
    fitted_by_process = Q1 @ projected
    residuals = target - fitted_by_process
    previous = None
    # Each residual column contiguous (Fortran order): its norm and its products with Q1 read
    # it in one stretch, a quarter of an iteration's time on Silverbox's 65 000 rows.
    lagged = np.empty((target.size, noise_lags), order="F")
    converged = False
    iterations = 0
    while iterations < max_iter and not converged:
        for first, last in pairwise(starts):
            for i in range(1, noise_lags + 1):
                column = lagged[first:last, i - 1]
                column[:i] = 0.0
                column[i:] = residuals[first : last - i]
        step = _extended_step(Q1, R1, projected, fitted_by_process, process_scale, lagged, target, names)
        iterations += 1
        # Relaxed: the same fixed point as feeding the new residual back unchanged, which
        # oscillates about it where the plain iteration does not settle.
        residuals = 0.5 * (residuals + target - step.fitted)
        if previous is not None:
            converged = bool(np.all(np.abs(step.theta - previous) / step.standard_errors < rtol))
        previous = step.theta
    return step, iterations, converged


@dataclass(frozen=True)
class PredictionErrorFit:
    """The prediction-error estimates θ̂ (process) and ĉ (noise), the covariance of [θ̂; ĉ],
    σ̂² = mean(ξ²), the Gauss–Newton steps taken and whether the search converged."""

    theta: np.ndarray
    noise: np.ndarray
    covariance: np.ndarray
    sigma2: float
    iterations: int
    converged: bool


def prediction_error(
    Phi: np.ndarray,
    target: np.ndarray,
    starts: np.ndarray,
    theta: np.ndarray,
    noise: np.ndarray,
    names: Sequence[str],
    max_iter: int,
    rtol: float,
) -> PredictionErrorFit:
    """Minimise Σξ², ξ = (target − Φθ)/C(q) on each record (rows ``starts[j]`` … ``starts[j+1]``),
    over θ and the moving-average coefficients c by Gauss–Newton from ``theta``, ``noise``
    (module docstring); Φ may have no columns (a moving average of ``target`` alone). ``names``
    name Φ's columns, then the c_i."""
    n = Phi.shape[0]
    innovations = _filtered(target - Phi @ theta, noise, starts)
    cost = float(innovations @ innovations)
    iterations, converged = 0, False
    while True:
        # ξ = J·δ by least squares, J = [Φ/C | q⁻ⁱ ξ/C] (the Jacobian of −ξ), in scaled columns.
        jacobian = np.hstack(
            [
                _filtered(Phi, noise, starts),
                _lagged(_filtered(innovations, noise, starts), noise.size, starts),
            ]
        )
        Q, R, scale, _ = scaled_qr(jacobian, names)
        step = linalg.solve_triangular(R, Q.T @ innovations) / scale
        covariance = scaled_covariance(R, scale, cost / n)
        converged = bool(np.all(np.abs(step) < rtol * np.sqrt(np.diag(covariance))))
        if converged or iterations == max_iter:
            break
        trial = _shortened_step(Phi, target, starts, theta, noise, step, cost)
        if trial is None:
            break
        theta, noise, innovations, cost = trial
        iterations += 1
    return PredictionErrorFit(theta, noise, covariance, cost / n, iterations, converged)


def _shortened_step(
    Phi: np.ndarray,
    target: np.ndarray,
    starts: np.ndarray,
    theta: np.ndarray,
    noise: np.ndarray,
    step: np.ndarray,
    cost: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Gauss–Newton's ``step`` from (θ, c), halved until Σξ² falls below ``cost``: the new θ, c,
    ξ and Σξ²; None where no step down to ``MIN_STEP`` of it lowers the sum."""
    k = Phi.shape[1]
    length = 1.0
    while length >= MIN_STEP:
        trial_theta = theta + length * step[:k]
        trial_noise = invertible(noise + length * step[k:])
        innovations = _filtered(target - Phi @ trial_theta, trial_noise, starts)
        trial_cost = float(innovations @ innovations)
        if trial_cost < cost:
            return trial_theta, trial_noise, innovations, trial_cost
        length /= 2
    return None


def moving_average(
    residuals: Sequence[np.ndarray], lags: int, max_iter: int = 100, rtol: float = 1e-2
) -> np.ndarray:
    """The coefficients c_1 … c_q (q = ``lags``) of e[t] = ξ[t] + Σ c_i·ξ[t−i], ξ white, that
    minimise the one-step prediction error Σ ξ² of the ``residuals`` e of each record (no lag
    crossing from one to the next): :func:`prediction_error` with no process terms, from Hannan
    and Rissanen's estimate."""
    records = [np.asarray(e, dtype=np.float64) for e in residuals]
    target = np.concatenate(records)
    starts = np.concatenate(([0], np.cumsum([e.size for e in records])))
    names = [f"e[t-{i}]" for i in range(1, lags + 1)]
    start = invertible(_hannan_rissanen(records, lags))
    fit = prediction_error(
        np.zeros((target.size, 0)), target, starts, np.empty(0), start, names, max_iter, rtol
    )
    return fit.noise


def _hannan_rissanen(records: Sequence[np.ndarray], lags: int) -> np.ndarray:
    """Hannan and Rissanen's moving-average estimate: the innovations estimated as the residual of
    a long autoregression, then e regressed on their lags."""
    order = LONG_AR_FACTOR * lags
    rows = [(record_lags(e, order), e) for e in records if e.size > order]
    if not rows:  # records too short for the long autoregression: from white innovations
        rows = [(np.zeros((e.size, 0)), e) for e in records]
        order = 0
    ar, *_ = np.linalg.lstsq(
        np.vstack([a for a, _ in rows]), np.concatenate([e for _, e in rows]), rcond=None
    )
    innovations = [e - record_lags(e, order) @ ar for e in records]
    lagged = np.vstack([record_lags(xi, lags) for xi in innovations])
    coefficients, *_ = np.linalg.lstsq(lagged, np.concatenate(records), rcond=None)
    return coefficients


def innovations_of(records: Sequence[np.ndarray], coefficients: np.ndarray) -> list[np.ndarray]:
    """ξ = e / C(q) on each record, from rest at its start."""
    denominator = np.concatenate(([1.0], coefficients))
    return [scipy.signal.lfilter([1.0], denominator, e) for e in records]


def _filtered(series: np.ndarray, noise: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """``series`` (a column or columns of stacked records) through 1/C(q), each record's rows
    from rest at its start."""
    if not noise.size or series.size == 0:
        return series.copy()
    denominator = np.concatenate(([1.0], noise))
    out = np.empty(series.shape, order="F")
    for first, last in pairwise(starts):
        out[first:last] = scipy.signal.lfilter([1.0], denominator, series[first:last], axis=0)
    return out


def _lagged(series: np.ndarray, lags: int, starts: np.ndarray) -> np.ndarray:
    """Columns series[t−1] … series[t−lags] of stacked records, zero before each record's start."""
    columns = np.zeros((series.size, lags), order="F")
    for first, last in pairwise(starts):
        for i in range(1, min(lags, last - first - 1) + 1):
            columns[first + i : last, i - 1] = series[first : last - i]
    return columns


def record_lags(series: np.ndarray, lags: int) -> np.ndarray:
    """Columns series[t−1] … series[t−lags] of one record, zero before its start."""
    return _lagged(series, lags, np.array([0, series.size]))


@dataclass(frozen=True)
class _Step:
    """One extended least-squares fit on [Φ | E]: estimates, covariance, σ̂² and fitted values."""

    theta: np.ndarray
    covariance: np.ndarray
    sigma2: float
    fitted: np.ndarray

    @property
    def standard_errors(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def _extended_step(
    Q1: np.ndarray,
    R1: np.ndarray,
    projected: np.ndarray,
    fitted_by_process: np.ndarray,
    process_scale: np.ndarray,
    lagged: np.ndarray,
    target: np.ndarray,
    names: Sequence[str],
) -> _Step:
    """Least squares on [Φ | E] given Φ/s = Q1·R1, Q1ᵀy and Q1Q1ᵀy.

    With C = Q1ᵀE (E column-scaled), E's part orthogonal to Φ is E⊥ = E − Q1·C, and
    E⊥ᵀE⊥ = EᵀE − CᵀC = R2ᵀR2 (Cholesky): the noise coefficients solve R2ᵀR2·γ = Eᵀy − Cᵀ·Q1ᵀy,
    the process ones R1·β = Q1ᵀy − C·γ, and [[R1, C], [0, R2]] is the triangular factor of the
    scaled [Φ | E]. One pass over Q1 for C and one for the fitted values Q1Q1ᵀy + E·γ − Q1·(Cγ).
    """
    noise_scale = np.linalg.norm(lagged, axis=0)
    noise_scale[noise_scale == 0] = 1.0
    E = lagged / noise_scale
    coupling = (E.T @ Q1).T  # Q1ᵀE, which OpenBLAS computes faster this way round
    try:
        R2 = linalg.cholesky(E.T @ E - coupling.T @ coupling)
    except linalg.LinAlgError:
        R2 = np.zeros((E.shape[1], E.shape[1]))  # E within Φ's span: refused just below
    k, q = R1.shape[0], R2.shape[0]
    R = np.zeros((k + q, k + q))
    R[:k, :k], R[:k, k:], R[k:, k:] = R1, coupling, R2
    checked_condition(R, names)
    gamma = linalg.cho_solve((R2, False), E.T @ target - coupling.T @ projected)
    beta = linalg.solve_triangular(R1, projected - coupling @ gamma)
    fitted = fitted_by_process + E @ gamma - Q1 @ (coupling @ gamma)
    sigma2 = float(np.mean((target - fitted) ** 2))
    scale = np.concatenate([process_scale, noise_scale])
    return _Step(np.concatenate([beta, gamma]) / scale, scaled_covariance(R, scale, sigma2), sigma2, fitted)


def invertible(noise: ArrayLike) -> np.ndarray:
    """The moving-average coefficients with every root of C(z) = 1 + Σ c_i z⁻ⁱ inside the unit
    circle, as the innovations filter 1/C(q) needs to be stable.

    A root r outside is replaced by 1/r̄, which leaves the noise spectrum's shape unchanged (it
    scales it by |r|², absorbed in the innovation variance); a root on the circle is pulled just
    inside. Extended least squares can settle on either factor; only this one predicts.
    """
    coefficients = np.asarray(noise, dtype=np.float64)
    if coefficients.size == 0:
        return coefficients
    roots = np.roots(np.concatenate(([1.0], coefficients)))
    radius = np.abs(roots)
    if np.all(radius < 1.0):
        return coefficients
    roots = np.where(radius > 1.0, 1.0 / np.conj(roots), roots)
    roots = np.where(np.abs(roots) >= 1.0 - 1e-6, roots * (1.0 - 1e-6), roots)
    return np.real(np.poly(roots))[1:]
