"""The inspection chain (SPEC §5): magnitude estimation, detection, localisation, interval.

For a fault-mode model V with residual e[t; k] = y[t] − φ[t]ᵀΘ·g(k):

1. k̂_V = argmin_k Σ e²[t; k] on [k_min, k_max] by bounded Brent search; σ̂_e² = mean(e²[t; k̂]).
2. σ̂_k² = σ̂_e² / Σ_t (∂e[t; k]/∂k)² at k̂ (Gauss–Newton), plus, by default, the delta-method
   term ∇ₖ(θ)ᵀ·Cov(θ)·∇ₖ(θ) for the estimation error of the fault-mode model itself.
3. Detection: a fault when |k̂_V| > z·σ̂_k for some V (the paper's test), or when even the
   best-fitting mode leaves a residual its Ljung–Box test finds grossly non-white — the record
   is then unlike every known state, the healthy one included (a fault of a mode no model
   describes need not move any k̂: the paper's case IV against the k2 model alone). This
   adequacy test takes a small share α_Q of α (2 %, 0.001 at α = 0.05): it is meant for gross failures,
   whose Q runs to hundreds, and Ljung–Box's upper tail is too heavy at N ≈ 2000, h = 40 for
   a larger share to keep its nominal size (bench/false_alarms.py: 2.1 % observed at 1.7 %, and
   twice the nominal rate at 0.1 % on white noise). The M magnitude tests
   share the rest by Šidák, each at 1 − ((1 − α)/(1 − α_Q))^{1/M}, so the overall false-alarm
   rate stays at or below α (the tests share one record and are positively dependent, which
   only makes this safer).
4. Localisation: Ljung–Box Q on each mode's residuals; a mode is accepted when
   Q < χ²_{1−α}(h − 1), and every mode's figures are recorded. The candidate is the mode with
   the smallest residual variance (the maximum-likelihood mode for Gaussian residuals); the
   fault is localised to it when its Q test accepts it, and is an ``unknown_fault`` when not.
   (Choosing among accepted modes instead would let a wrong mode win whenever the right one
   fails its 5 % test by chance: a wrong stiffness mode can leave a residual that is white,
   because the excitation is white, yet a hundred times larger.)
5. Magnitude: k̂ ± z_{1−α/2}·σ̂_k from the reported mode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from models.diagnostics import ljung_box
from models.errors import InputError
from models.fnarx import FNARX
from models.narx import z_quantile
from models.signals import Record, checked_record, minimum_samples
from models.terms import max_degree, regressor_matrix

# Every status a verdict can have: ``anomaly`` is a healthy baseline's alone (models.novelty), a
# record unlike its healthy records that no fault mode describes.
Status = Literal["healthy", "faulty", "unknown_fault", "anomaly"]
GRID_POINTS = 129
ADEQUACY_SHARE = 0.02  # of α: 0.001 at α = 0.05


@dataclass(frozen=True)
class MagnitudeEstimate:
    """k̂ of one fault-mode model on one record (SPEC §5, steps 1–2).

    ``sigma_k`` includes the fault-mode model's own estimation error when requested;
    ``sigma_k_record`` is the paper's σ̂_k from the record's residual alone.
    """

    k_hat: float
    sigma_k: float
    sigma_k_record: float
    sigma_e2: float
    residuals: np.ndarray
    at_range_limit: bool


@dataclass(frozen=True)
class ModeResult:
    """Every figure the chain computes for one fault mode."""

    name: str
    k_hat: float
    sigma_k: float
    sigma_k_record: float
    z: float
    detects: bool
    residual_variance: float
    q: float
    q_critical: float
    p_value: float
    accepted: bool
    at_range_limit: bool


@dataclass(frozen=True)
class Verdict:
    """The outcome of inspecting one record against a set of fault-mode models.

    ``k_hat``, ``sigma_k`` and ``interval`` come from ``reference_mode``, the mode that best
    describes the record; they are None for an unknown fault (no model describes it, so no
    magnitude is estimated). ``z_critical`` is None when no fault mode was tested: a healthy
    baseline's check alone (:func:`models.pooled.baseline_verdict`); ``q_critical_detection`` is
    None when no whiteness test detects: a vector inspection (:func:`models.vector.vector_verdict`);
    ``lags`` is None when no Ljung–Box test is made: a healthy baseline's judgement alone
    (:mod:`models.novelty`).
    """

    status: Status
    fault_detected: bool
    fault_mode: str | None
    reference_mode: str | None
    k_hat: float | None
    sigma_k: float | None
    interval: tuple[float, float] | None
    alpha: float
    lags: int | None
    n_samples: int
    z_critical: float | None
    q_critical_detection: float | None
    detected_by: tuple[str, ...]
    modes: tuple[ModeResult, ...]

    def mode(self, name: str) -> ModeResult:
        """The figures of the fault mode called ``name``."""
        for mode in self.modes:
            if mode.name == name:
                return mode
        raise KeyError(f"no fault mode {name!r} in this verdict")

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: the figures by their names, the modes' as dicts."""
        document = asdict(self)
        document["interval"] = list(self.interval) if self.interval is not None else None
        document["detected_by"] = list(self.detected_by)
        document["modes"] = list(document["modes"])  # asdict has made each mode a dict
        return document


def estimate_magnitude(
    model: FNARX, x: ArrayLike, y: ArrayLike, *, model_uncertainty: bool = True
) -> MagnitudeEstimate:
    """Estimate the fault magnitude of a record under one fault-mode model (steps 1–2)."""
    xa, ya = checked_record(x, y, model.max_lag + len(model.terms) + 1)
    Phi, target = regressor_matrix(model.terms, xa, ya)
    return _estimate(model, Phi, target, model_uncertainty)


def inspect(
    x: ArrayLike,
    y: ArrayLike,
    fault_modes: Sequence[FNARX],
    *,
    alpha: float = 0.05,
    lags: int = 40,
    adequacy_share: float = ADEQUACY_SHARE,
    model_uncertainty: bool = True,
) -> Verdict:
    """Run the whole chain on one record (x: excitation, y: response).

    Examples
    --------
    One fault mode, trained from experiments at 0, 10 and 20 %, judging a record at 15 %:

    >>> import numpy as np
    >>> from scipy.signal import lfilter
    >>> def record(k, seed):  # y[t] = 0.5·(1 − k/100)·y[t-1] + x[t-1] + e[t]
    ...     x, e = np.random.default_rng(seed).standard_normal((2, 2000))
    ...     return x, lfilter([1.0], [1.0, -0.5 * (1 - k / 100)], np.r_[0.0, x[:-1]] + 0.05 * e)
    >>> from models.fnarx import fit_fnarx
    >>> experiments = [(*record(k, seed), k) for seed, k in enumerate((0.0, 10.0, 20.0))]
    >>> mode = fit_fnarx(experiments, ["y[t-1]", "x[t-1]"], name="pole")
    >>> verdict = inspect(*record(15.0, 99), [mode])
    >>> verdict.status, verdict.fault_mode, round(verdict.k_hat)
    ('faulty', 'pole', 15)
    >>> inspect(*record(0.0, 98), [mode]).status
    'healthy'
    """
    check_request([model.name for model in fault_modes], alpha, adequacy_share)
    adequacy_alpha = adequacy_share * alpha
    if int(lags) != lags or lags < 2:
        raise InputError(f"lags must be a whole number of at least 2, got {lags}")
    longest_lag = max(model.max_lag for model in fault_modes)
    xa, ya = checked_for_inspection(x, y, fault_modes, int(lags))

    magnitude_level = 1 - ((1 - alpha) / (1 - adequacy_alpha)) ** (1 / len(fault_modes))
    z_detect = z_quantile(1 - magnitude_level)
    q_detect = float(special.chdtri(int(lags) - 1, adequacy_alpha))
    modes = []
    regressors: dict[tuple[Any, ...], tuple[np.ndarray, np.ndarray]] = {}
    for model in fault_modes:
        key = model.terms
        if key not in regressors:
            regressors[key] = regressor_matrix(model.terms, xa, ya, longest_lag)
        estimate = _estimate(model, *regressors[key], model_uncertainty)
        whiteness = ljung_box(estimate.residuals, int(lags), alpha)
        z = estimate.k_hat / estimate.sigma_k
        modes.append(
            ModeResult(
                name=model.name,
                k_hat=estimate.k_hat,
                sigma_k=estimate.sigma_k,
                sigma_k_record=estimate.sigma_k_record,
                z=z,
                detects=bool(abs(z) > z_detect),
                residual_variance=estimate.sigma_e2,
                q=whiteness.q,
                q_critical=whiteness.q_critical,
                p_value=whiteness.p_value,
                accepted=whiteness.white,
                at_range_limit=estimate.at_range_limit,
            )
        )
    _check_finite(modes)
    return _decide(modes, alpha, int(lags), len(ya), z_detect, q_detect)


def check_request(names: Sequence[str], alpha: float, adequacy_share: float) -> None:
    """Refuse an inspection without fault modes, with two of one name, or with an α or adequacy
    share the tests cannot be designed at."""
    if not names:
        raise InputError("inspection needs at least one fault-mode model")
    if len(set(names)) != len(names):
        raise InputError(f"fault-mode model names must be distinct, got {list(names)}")
    if not 0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    if not 0 < adequacy_share < 1:
        raise InputError(f"the adequacy test's share of alpha must lie in (0, 1), got {adequacy_share}")


def checked_for_inspection(x: ArrayLike, y: ArrayLike, fault_modes: Sequence[FNARX], lags: int) -> Record:
    """(x, y) as float64 vectors fit to be inspected with ``fault_modes`` at ``lags`` Ljung–Box lags.

    Long enough for the residual tests after the models' longest lag
    (:func:`models.signals.minimum_samples`), and no value so large that the models' terms of
    highest degree overflow the statistics (:func:`models.signals.magnitude_limit`). A service
    that queues an inspection checks a record with this before storing it, so that the queued
    inspection cannot fail on what the upload could have refused.
    """
    longest_lag = max(model.max_lag for model in fault_modes)
    degree = max_degree([term for model in fault_modes for term in model.terms])
    return checked_record(x, y, minimum_samples(lags, longest_lag), degree=degree)


def _check_finite(modes: list[ModeResult]) -> None:
    """Refuse a record whose statistics came out infinite or NaN.

    The magnitude bound keeps the record's own sums of squares finite, but a model's extreme
    coefficients can still overflow the residual of an ordinary record; a verdict built on an
    infinite or NaN figure would be stored as healthy with its statistics lost.
    """
    for mode in modes:
        for field, value in asdict(mode).items():
            if isinstance(value, float) and not np.isfinite(value):
                raise InputError(
                    f"inspecting the record with fault mode {mode.name!r} gives a non-finite {field} "
                    f"({value}): its values are too large or too small for the model; rescale the record "
                    "(e.g. to SI units)"
                )


def _decide(
    modes: list[ModeResult], alpha: float, lags: int, n: int, z_detect: float, q_detect: float
) -> Verdict:
    best = min(modes, key=lambda mode: mode.residual_variance)
    detected_by = tuple(mode.name for mode in modes if mode.detects)
    if best.q > q_detect:
        detected_by += ("whiteness",)
    if not detected_by:
        status: Status = "healthy"
    elif best.accepted:
        status = "faulty"
    else:
        status = "unknown_fault"
    reference = None if status == "unknown_fault" else best
    z = z_quantile(1 - alpha)
    return Verdict(
        status=status,
        fault_detected=bool(detected_by),
        fault_mode=best.name if status == "faulty" else None,
        reference_mode=reference.name if reference else None,
        k_hat=reference.k_hat if reference else None,
        sigma_k=reference.sigma_k if reference else None,
        interval=(reference.k_hat - z * reference.sigma_k, reference.k_hat + z * reference.sigma_k)
        if reference
        else None,
        alpha=alpha,
        lags=lags,
        n_samples=n,
        z_critical=z_detect,
        q_critical_detection=q_detect,
        detected_by=detected_by,
        modes=tuple(modes),
    )


def _estimate(
    model: FNARX, Phi: np.ndarray, target: np.ndarray, model_uncertainty: bool
) -> MagnitudeEstimate:
    basis = model.basis
    Z = Phi @ model.theta  # column j: the prediction carried by G_j
    k_hat = _minimise_sse(model, Z, target)
    residuals = target - Z @ basis.values(k_hat)
    sigma_e2 = float(np.mean(residuals**2))
    slope = Z @ basis.derivatives(k_hat)  # −∂e/∂k
    information = float(slope @ slope)
    if not information > 0:
        raise InputError(
            f"the record carries no information on the magnitude of fault mode {model.name!r}: "
            "the residual does not depend on k (is the excitation zero?)"
        )
    variance_record = sigma_e2 / information
    variance = variance_record
    if model_uncertainty:
        gradient = np.kron(Phi.T @ slope, basis.values(k_hat)) / information
        variance += float(gradient @ model.covariance @ gradient)
    span = basis.k_max - basis.k_min
    limit = min(k_hat - basis.k_min, basis.k_max - k_hat) < 1e-6 * span
    return MagnitudeEstimate(
        k_hat, float(np.sqrt(variance)), float(np.sqrt(variance_record)), sigma_e2, residuals, limit
    )


def _minimise_sse(model: FNARX, Z: np.ndarray, target: np.ndarray) -> float:
    """argmin Σe²(k) on the model's range, from the roots of the derivative near the best point
    of a coarse grid.

    Σe² is a polynomial in u (the normalised magnitude) of degree 2(p − 1). Its coefficients lose
    precision far from where they are expanded, so they are expanded again around the best grid
    point u0, and the minimum within a grid step of it is the least of Σe² at the ends of that
    interval and at the real parts of the roots of d(Σe²)/dδ that fall inside it (a complex
    pair's real part is a harmless extra candidate). Exact up to the roots' rounding, where a
    search comparing values stops at √(eps·Σe²/g) from the minimum (g the curvature).
    """
    basis = model.basis
    W = Z @ basis.power_coefficients  # predictions carried by the powers u⁰, u¹, …
    grid = np.linspace(-1.0, 1.0, GRID_POINTS)
    best = grid[int(np.argmin(np.polyval(_sse_polynomial(W, target, 0.0), grid)))]
    step = grid[1] - grid[0]
    around_best = _sse_polynomial(W, target, best)
    low, high = max(-1.0 - best, -step), min(1.0 - best, step)
    candidates = np.array([low, high])
    derivative = np.polyder(around_best)
    if np.any(derivative) and np.all(np.isfinite(derivative)):  # non-finite: refused after
        candidates = np.concatenate([candidates, np.clip(np.roots(derivative).real, low, high)])
    delta = float(candidates[int(np.argmin(np.polyval(around_best, candidates)))])
    return float(basis.k_min + (best + delta + 1.0) * (basis.k_max - basis.k_min) / 2)


@lru_cache(maxsize=16)
def _shift_table(p: int) -> tuple[np.ndarray, np.ndarray]:
    """C(i, m) for m ≤ i (0 above) and the exponents i − m (0 above) of u^i = Σ_m C(i, m)·u0^{i−m}·δ^m."""
    i, m = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
    binomials, exponents = np.where(m <= i, special.comb(i, m), 0.0), np.maximum(i - m, 0)
    binomials.flags.writeable = exponents.flags.writeable = False  # shared by every caller
    return binomials, exponents


def _sse_polynomial(W: np.ndarray, target: np.ndarray, u0: float) -> np.ndarray:
    """Coefficients (highest power first) of Σe² as a polynomial in δ = u − u0.

    With e = target − W·[u⁰ … u^{p−1}] and u^i = Σ_m C(i, m)·u0^{i−m}·δ^m, the residual is
    r − Σ_{m≥1} V_m·δ^m with r the residual at u0.
    """
    p = W.shape[1]
    binomials, exponents = _shift_table(p)
    Ws = W @ (binomials * u0**exponents)
    r = target - Ws[:, 0]
    V = Ws[:, 1:]
    cross = V.T @ r
    gram = V.T @ V
    ascending = np.zeros(2 * p - 1)
    ascending[0] = r @ r
    ascending[1:p] -= 2 * cross
    for a in range(1, p):
        ascending[a + 1 : a + p] += gram[a - 1]
    return ascending[::-1]
