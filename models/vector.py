"""Vector fault-mode models: several response channels judged together.

A structure carrying K sensors gives K responses y_1 … y_K to the force x. A vector functional
ARX model of fault mode V holds one equation per channel, each free to use every channel's lags:

    y[t] = Σ_{i=1..p} A_i(k)·y[t−i] + Σ_{i=1..p} b_i(k)·x[t−i] + e[t],   e[t] ~ (0, Σ),

with every coefficient a function of the fault magnitude k on a functional basis g(k)
(:mod:`models.basis`), as an FNARX's are: Y = (Φ ⊗ g(k))·Θ with Φ[t] = (y[t−1..p], x[t−1..p]),
Θ estimated by least squares over experiments at several k (one regression, K right-hand sides).
A chain of masses and springs discretised by forward differences is exactly such a model of its
displacements (p = 2, the coefficients affine in each stiffness), with the force disturbance as
e; a single sensor sees the same structure only through an ARX model of order 2n whose equation
error is the disturbance filtered.

The inspection of a record (x, y) estimates, for each mode, k̂ = argmin_k Σ_t e_t(k)ᵀ·Σ̂⁻¹·e_t(k)
(generalised least squares with the model's residual covariance; for K = 1 the scalar inspection's
criterion), its standard error by Gauss–Newton, σ̂_k² = 1/Σ_t ∂e_tᵀ·Σ̂_r⁻¹·∂e_t (Σ̂_r the record's
own residual covariance at k̂), and the vector residual's whiteness by Hosking's portmanteau test
(:func:`models.diagnostics.hosking`, one parameter estimated). As in :mod:`models.inspection`, the
candidate mode is the maximum-likelihood one — the smallest generalised residual variance
det Σ̂_r — and a detected fault is localised to it. Unlike the scalar chain, the localisation does
not wait for that mode's residual to be white: a sensor's noise v enters every channel's equation
through (1 − q⁻¹)²·v (the discretised second derivative), a moving average with roots on the unit
circle that no finite lag order whitens, so with measured displacements Hosking's test rejects
every mode, the right one included, while the likelihood still tells them apart. Its figures are
recorded with each mode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy
from numpy.typing import ArrayLike

from models.basis import BasisFamily, FunctionalBasis
from models.diagnostics import HoskingResult, hosking
from models.errors import InputError
from models.inspection import ModeResult, Verdict
from models.narx import DOCUMENT_VERSION, check_document, z_quantile

VectorExperiment = tuple[ArrayLike, ArrayLike, float]  # x (N,), y (N, K), k [%]


@dataclass(frozen=True)
class VectorFNARX:
    """A vector fault-mode model: Y = (Φ ⊗ g(k))·Θ + E (module docstring).

    Attributes
    ----------
    name : the fault mode, e.g. ``"k3"``.
    lags : p, the lags of every channel and of the input in Φ.
    channels : K, the number of response channels.
    basis : g(k) over the magnitudes of the training experiments.
    theta : Θ, shape (Φ's columns · basis size, K), rows ordered column of Φ, then basis function.
    sigma : Σ̂, the residual covariance over the training experiments, shape (K, K).
    """

    name: str
    lags: int
    channels: int
    basis: FunctionalBasis
    theta: np.ndarray
    sigma: np.ndarray

    def components(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The target Y[t] (t = p … N−1) and, for each basis function b, Φ·Θ_b: the residual at
        k is Y − Σ_b g_b(k)·(Φ·Θ_b), shape (basis size, N − p, K)."""
        phi = regressors(x, y, self.lags)
        size = self.basis.size
        parts = np.stack([phi @ self.theta[b::size] for b in range(size)])
        return y[self.lags :], parts

    def residual(self, x: ArrayLike, y: ArrayLike, k: float) -> np.ndarray:
        """e[t] = y[t] − ŷ[t; k] for t = p … N−1, shape (N − p, K)."""
        xa, ya = checked_vector_record(x, y, self.lags, self.channels)
        target, parts = self.components(xa, ya)
        return target - np.tensordot(self.basis.values(float(k)), parts, axes=1)

    def to_document(self) -> dict[str, Any]:
        return {
            "kind": "vector",
            "schema_version": DOCUMENT_VERSION,
            "name": self.name,
            "lags": self.lags,
            "channels": self.channels,
            "basis": self.basis.to_document(),
            "theta": self.theta.tolist(),
            "sigma": self.sigma.tolist(),
        }

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> VectorFNARX:
        check_document(document, "vector")
        lags, channels = int(document["lags"]), int(document["channels"])
        basis = FunctionalBasis.from_document(document["basis"])
        theta = np.asarray(document["theta"], dtype=np.float64)
        sigma = np.asarray(document["sigma"], dtype=np.float64)
        if theta.shape != ((channels + 1) * lags * basis.size, channels) or sigma.shape != (
            channels,
            channels,
        ):
            raise InputError("vector model document: theta and sigma do not match its lags and channels")
        return cls(str(document["name"]), lags, channels, basis, theta, sigma)


def regressors(x: np.ndarray, y: np.ndarray, lags: int) -> np.ndarray:
    """Φ[t] = (y_1..K[t−1], …, y_1..K[t−p], x[t−1], …, x[t−p]) for t = p … N−1."""
    n = len(x)
    columns = [y[lags - i : n - i] for i in range(1, lags + 1)]
    columns += [x[lags - i : n - i, None] for i in range(1, lags + 1)]
    return np.hstack(columns)


def checked_vector_record(
    x: ArrayLike, y: ArrayLike, lags: int, channels: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """x as (N,) and y as (N, K) float arrays, refused when they disagree in length, hold values
    that are not finite, have another number of channels than ``channels``, or are too short."""
    xa = np.asarray(x, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    if ya.ndim == 1:
        ya = ya[:, None]
    if xa.ndim != 1 or ya.ndim != 2 or len(xa) != len(ya):
        raise InputError(
            "a record is x of N samples and y of N samples on each of K channels; "
            f"got x {xa.shape} and y {ya.shape}"
        )
    if channels is not None and ya.shape[1] != channels:
        raise InputError(f"the model judges {channels} response channels; the record has {ya.shape[1]}")
    if len(xa) <= 2 * lags + 1:
        raise InputError(f"a record of {len(xa)} samples is too short for a model of {lags} lags")
    if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(ya))):
        raise InputError("the record holds values that are not finite")
    return xa, ya


def fit_vector_fnarx(
    name: str,
    experiments: Sequence[VectorExperiment],
    lags: int = 2,
    basis_size: int = 2,
    family: BasisFamily = "chebyshev2",
) -> VectorFNARX:
    """Estimate a vector fault-mode model by least squares over ``experiments`` (x, y, k), each
    y an (N, K) array of the same K channels and k its fault magnitude in percent."""
    if lags < 1:
        raise InputError(f"lags must be 1 or more, got {lags}")
    if len(experiments) < basis_size:
        raise InputError(
            f"{len(experiments)} experiments cannot determine a basis of {basis_size} functions of k"
        )
    ks = np.array([float(k) for *_, k in experiments])
    if np.ptp(ks) == 0:
        raise InputError("every experiment has the same fault magnitude: a function of k needs several")
    basis = FunctionalBasis(family, basis_size, float(ks.min()), float(ks.max()))
    checked = [checked_vector_record(x, y, lags) for x, y, _ in experiments]
    channels = checked[0][1].shape[1]
    if any(y.shape[1] != channels for _, y in checked):
        raise InputError("every experiment must carry the same response channels")
    blocks = []
    targets = []
    for (x, y), k in zip(checked, ks, strict=True):
        phi = regressors(x, y, lags)
        blocks.append((phi[:, :, None] * basis.values(k)[None, None, :]).reshape(len(phi), -1))
        targets.append(y[lags:])
    design = np.vstack(blocks)
    target = np.vstack(targets)
    if np.linalg.matrix_rank(design) < design.shape[1]:
        raise InputError("the experiments do not determine every coefficient: the design is rank-deficient")
    theta, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = target - design @ theta
    sigma = residual.T @ residual / (len(target) - design.shape[1])
    return VectorFNARX(name, lags, channels, basis, theta, sigma)


@dataclass(frozen=True)
class VectorModeResult:
    """One mode's figures on one record: k̂ [%], σ̂_k [%], the generalised residual variance
    det Σ̂_r, the vector residual's whiteness and each channel's residual RMS (its units)."""

    name: str
    k_hat: float
    sigma_k: float
    generalised_variance: float
    whiteness: HoskingResult
    channel_rms: tuple[float, ...]


@dataclass(frozen=True)
class VectorInspection:
    """The modes' figures and the verdict: whether a fault is detected, and the mode it is
    localised to (the maximum-likelihood mode; None when no fault is detected); ``z_critical``
    is the magnitude tests' critical |k̂|/σ̂_k."""

    modes: tuple[VectorModeResult, ...]
    detected: bool
    localised: str | None
    z_critical: float


def inspect_vector(
    x: ArrayLike, y: ArrayLike, modes: Sequence[VectorFNARX], alpha: float = 0.05, lags: int = 40
) -> VectorInspection:
    """Detect, localise and size a fault from every response channel at once (module docstring).

    Detection: |k̂| > z_{1−α_M/2}·σ̂_k for some mode, α_M = 1 − (1 − α)^{1/M} (Šidák over the M
    modes, as the scalar inspection's magnitude tests)."""
    if not modes:
        raise InputError("at least one fault-mode model is needed")
    results = tuple(_judge(mode, x, y, alpha, lags) for mode in modes)
    z = z_quantile((1 - alpha) ** (1 / len(modes)))  # two-sided at α_M: z_{1−α_M/2}
    detected = any(abs(r.k_hat) > z * r.sigma_k for r in results)
    best = min(results, key=lambda r: r.generalised_variance)
    localised = best.name if detected else None
    return VectorInspection(results, detected, localised, z)


@dataclass(frozen=True)
class VectorModeFigures(ModeResult):
    """A vector mode's figures in the scalar chain's fields (:func:`vector_verdict`), with each
    channel's residual RMS by channel name."""

    channel_rms: dict[str, float]


def vector_verdict(
    inspection: VectorInspection,
    modes: Sequence[VectorFNARX],
    channels: Sequence[str],
    alpha: float,
    lags: int,
    n_samples: int,
) -> Verdict:
    """A vector inspection as the scalar chain's :class:`models.inspection.Verdict`, so that it is
    stored, listed and alarmed on as any other. Per mode: ``residual_variance`` is the generalised
    variance det Σ̂_r, ``q``, ``q_critical``, ``p_value`` and ``accepted`` are Hosking's test of the
    vector residual, ``sigma_k_record`` is ``sigma_k`` (the record's own Gauss–Newton error), and
    ``channel_rms`` names each channel's residual RMS. ``faulty`` when a magnitude test detects, in
    the maximum-likelihood mode (``reference_mode`` always: the localisation does not wait for
    whiteness, module docstring), else ``healthy``; never ``unknown_fault``, and
    ``q_critical_detection`` is None: no whiteness test detects."""
    figures = []
    for model, result in zip(modes, inspection.modes, strict=True):
        basis = model.basis
        edge = 1e-3 * (basis.k_max - basis.k_min)
        figures.append(
            VectorModeFigures(
                name=result.name,
                k_hat=result.k_hat,
                sigma_k=result.sigma_k,
                sigma_k_record=result.sigma_k,
                z=result.k_hat / result.sigma_k,
                detects=bool(abs(result.k_hat) > inspection.z_critical * result.sigma_k),
                residual_variance=result.generalised_variance,
                q=result.whiteness.q,
                q_critical=result.whiteness.q_critical,
                p_value=result.whiteness.p_value,
                accepted=result.whiteness.white,
                at_range_limit=min(result.k_hat - basis.k_min, basis.k_max - result.k_hat) < edge,
                channel_rms=dict(zip(channels, result.channel_rms, strict=True)),
            )
        )
    best = min(figures, key=lambda mode: mode.residual_variance)
    z = z_quantile(1 - alpha)
    return Verdict(
        status="faulty" if inspection.detected else "healthy",
        fault_detected=inspection.detected,
        fault_mode=inspection.localised,
        reference_mode=best.name,
        k_hat=best.k_hat,
        sigma_k=best.sigma_k,
        interval=(best.k_hat - z * best.sigma_k, best.k_hat + z * best.sigma_k),
        alpha=alpha,
        lags=lags,
        n_samples=n_samples,
        z_critical=inspection.z_critical,
        q_critical_detection=None,
        detected_by=tuple(mode.name for mode in figures if mode.detects),
        modes=tuple(figures),
    )


def _judge(mode: VectorFNARX, x: ArrayLike, y: ArrayLike, alpha: float, lags: int) -> VectorModeResult:
    xa, ya = checked_vector_record(x, y, mode.lags, mode.channels)
    target, parts = mode.components(xa, ya)
    weight = np.linalg.pinv(mode.sigma)
    basis = mode.basis

    def criterion(k: float) -> float:
        e = target - np.tensordot(basis.values(k), parts, axes=1)
        return float(np.einsum("ti,ij,tj->", e, weight, e))

    found = scipy.optimize.minimize_scalar(criterion, bounds=(basis.k_min, basis.k_max), method="bounded")
    k_hat = float(found.x)
    e = target - np.tensordot(basis.values(k_hat), parts, axes=1)
    slope = -np.tensordot(basis.derivatives(k_hat), parts, axes=1)  # ∂e/∂k
    covariance = e.T @ e / len(e)
    information = float(np.einsum("ti,ij,tj->", slope, np.linalg.pinv(covariance), slope))
    sigma_k = 1 / np.sqrt(information) if information > 0 else np.inf
    return VectorModeResult(
        mode.name,
        k_hat,
        float(sigma_k),
        float(np.linalg.det(covariance)),
        hosking(e, lags=lags, alpha=alpha, model_df=1),
        tuple(float(v) for v in np.sqrt(np.mean(e**2, axis=0))),
    )


def coefficients(model: VectorFNARX, k: float) -> tuple[np.ndarray, np.ndarray]:
    """The model at k: A (p, K, K), A[i−1] multiplying y[t−i], and B (p, K), B[i−1] multiplying x[t−i]."""
    size, channels, p = model.basis.size, model.channels, model.lags
    at_k = np.tensordot(
        model.basis.values(float(k)), model.theta.reshape(-1, size, channels), axes=([0], [1])
    )
    A = at_k[: channels * p].reshape(p, channels, channels).transpose(0, 2, 1)
    return A, at_k[channels * p :]


def simulate_vector(model: VectorFNARX, k: float, x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """Free run of the model at k driven by x, started from the first p measured samples of y
    (N, K); NaN from a sample whose magnitude passes 10¹⁰⁰ on (a diverged run)."""
    xa, ya = checked_vector_record(x, y, model.lags, model.channels)
    A, B = coefficients(model, k)
    p, n = model.lags, len(xa)
    lagged = np.column_stack([np.concatenate([np.zeros(i), xa[: n - i]]) for i in range(1, p + 1)])
    drive = lagged @ B
    out = ya.copy()
    companion = np.hstack(list(A))  # (K, K·p) acting on (y[t−1], …, y[t−p])
    for t in range(p, n):
        out[t] = companion @ out[t - 1 :: -1][:p].reshape(-1) + drive[t]
        if not np.all(np.abs(out[t]) < 1e100):
            out[t:] = np.nan
            break
    return out


def modal_parameters(model: VectorFNARX, k: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Natural frequencies [Hz] and damping ratios of the model's dynamics at k: each pole λ of
    the companion matrix of A_1 … A_p (upper half-plane only) mapped to s = fs·ln λ, f = |s|/2π,
    ζ = −Re s/|s|; sorted by frequency."""
    A, _ = coefficients(model, k)
    p, channels = model.lags, model.channels
    companion = np.zeros((channels * p, channels * p))
    companion[:channels] = np.hstack(list(A))
    companion[channels:, : channels * (p - 1)] = np.eye(channels * (p - 1))
    poles = np.linalg.eigvals(companion)
    poles = poles[poles.imag > 0]
    s = fs * np.log(poles)
    order = np.argsort(np.abs(s))
    return np.abs(s)[order] / (2 * np.pi), (-s.real / np.abs(s))[order]
