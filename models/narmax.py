"""NARMAX models by extended least squares: NARX process terms plus moving-average noise terms.

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
oscillates about it for ever (measured: 5 of 10 MA(2) records still moving by 0.1–0.3 s.e.
after 100 iterations); the relaxed iteration settled in 13–15 on all of them. Each record
keeps its own residual series, pre-windowed (ε = 0 before its first equation), so no lag
crosses records. The covariance is that of the last least-squares fit, which treats the
residual regressors as known: it understates the spread of θ̂ somewhat (by ~25 % in the
tests' Monte Carlo).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg

from models.errors import InputError
from models.narx import NARX
from models.regression import checked_condition, scaled_covariance, scaled_qr
from models.signals import checked_records
from models.terms import Term, max_degree, max_lag, parse_terms, stacked_regressors


@dataclass(frozen=True)
class NARMAX:
    """Process model and moving-average noise model estimated together.

    Attributes
    ----------
    process : the NARX part: terms, θ̂ and its covariance block, σ̂² = mean(ε²).
    noise : MA coefficients c_1 … c_q.
    noise_covariance : covariance of ĉ.
    iterations : least-squares fits after the initial one.
    converged : whether the last iteration moved every parameter by less than ``rtol`` s.e.
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
    # Φ stays fixed while the residual columns change: its QR is computed once (which also refuses
    # a degenerate design), and each iteration solves for the q new columns through the Schur
    # complement of Φ's block (a block QR update without forming E's orthogonal part).
    Q1, R1, process_scale, _ = scaled_qr(Phi, names[: len(parsed)])
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
        residuals = 0.5 * (residuals + target - step.fitted)
        if previous is not None:
            converged = bool(np.all(np.abs(step.theta - previous) / step.standard_errors < rtol))
        previous = step.theta
    # The last step is the least-squares fit on [Φ | E] with E the residual columns it was given.
    k = len(parsed)
    theta, covariance = step.theta, step.covariance
    process = NARX(parsed, theta[:k], covariance[:k, :k], step.sigma2, target.size)
    return NARMAX(process, theta[k:], covariance[k:, k:], iterations, converged)


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
