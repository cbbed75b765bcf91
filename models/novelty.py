"""Baseline-only monitoring: is a record unlike the healthy records a baseline was trained on?

A structure brought without fault experiments has a healthy baseline alone, and a record is
judged against it: ``healthy`` or ``anomaly``, at a false-alarm rate α that is designed, not tuned.

Why the simulation error, not the one-step residual. The inspection chain's residual is the
one-step prediction error, white when the noise enters the structure as a force (equation
error). A real sensor adds its noise to what it measures instead, and at a fast sampling rate the
one-step residual is then mostly that noise passed through the model's autoregressive part,
which nearly differences it: coloured, far above the healthy model's σ̂², and insensitive to the
structure (the lagged outputs it predicts from carry the change). The free run ŷ[t] of the
baseline driven by the measured force alone (:mod:`models.simulation`) has the error

    ε[t] = y[t] − ŷ[t] = n_y[t] − G·n_x[t] + (G_record − G_baseline)·x[t]   (linear case),

the sensor noise on y, the noise on x through the baseline, and what the structure's change
does to the response: the last is the whole difference a fault makes to the response, not its
shadow in one step. The free run starts from the initial outputs that minimise the error over
the record (:class:`models.output_error.EstimatedStart`), not from the first L measured ones:
from those, at a fast sampling rate, the run would carry their noise amplified by its ring-down,
and a baseline fitted so trades model error for a quiet start (a bias that grows with the
excitation squared). The baseline is to be fitted so too (``fit_output_error(…,
start_from="estimated")``), and must be linear in its output.

The statistic (units: the response's squared units, as ratios here, so none): the error's power
in B = ⌈M/2⌉ − 1 bands, against the healthy error's. A fault moves the error where it moves the
response, near the modes it changes, and there it stands out of the sensor noise far more than in
the total variance, which the noise over the whole band dilutes.

- reference (:func:`novelty_reference`): the healthy records' free-run errors from sample L on,
  out of sample (each from the baseline's terms fitted on the other records), cut into K₀
  segments of M samples; P̂₀(b) the mean over them of the periodogram
  I(b) = |Σ_t ε[t]·e^{−2πibt/M}|²/M, b = 1 … B; σ̂²₀ = Σε²/n₀ the total;
- a record's P̂(b), the mean over its K = ⌊(N − L)/M⌋ segments. For a Gaussian stationary error
  whose correlation is short beside M, I(b) ≈ S(b)·χ²₂/2, independent over bands and
  segments, so P̂(b) ≈ S(b)·χ²_ν/ν with ν = 2K, P̂₀(b) ≈ S(b)·χ²_{ν₀}/ν₀ with ν₀ = 2K₀, and
  F(b) = P̂(b)/P̂₀(b) ≈ F(ν, ν₀) whatever the error's spectrum S;
- the statistic max_b F(b) against the Šidák threshold F_{(1−α)^{1/B}}(ν, ν₀): all B bands stay
  below it with probability 1 − α. A record is an ``anomaly`` above it: one-sided, since a
  change of the structure adds to the error. p-value 1 − (1 − p_min)^B. ν scales with the record's
  length and ν₀ carries the reference's own uncertainty, so the rate holds for records shorter or
  longer than the training ones, and for other excitation levels as long as the sensor noise is
  a floor (its variance does not grow with the signal) and the baseline is at that floor.
- severity: s²/σ̂²₀, s² = mean ε²[t], t = L … N−1: how many times a healthy record's
  simulation-error variance the record's is; 1 when healthy, whatever the record's length, so
  a person can trend it.

A baseline whose linear part does not ring down within ``MAX_START_UP`` samples (a root on or
outside the unit circle, or too near it) is ``marginal``: its verdicts say so, for its free-run
error is not stationary and the design rate does not hold. A record whose free run diverges is
an ``anomaly`` whose verdict says so (``diverged_at``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy import special
from scipy.linalg import solve_discrete_lyapunov

from models.errors import InputError
from models.narx import NARX
from models.output_error import estimated_start_error, fit_output_error
from models.signals import checked_record, checked_records
from models.terms import max_degree

Status = Literal["healthy", "anomaly"]
FreeRunState = Literal["settled", "marginal", "diverged"]
DOCUMENT_VERSION = 2
# What is left of a start error after the start-up, in all, as a share of one sample's variance.
START_UP_SHARE = 1e-2
# The longest start-up a baseline may need before it counts as marginal.
MAX_START_UP = 50_000
# Error samples a record needs after its initial outputs, at least, for its statistic.
MIN_SAMPLES = 100
# Samples of a segment: 15 bands, each as wide as a heavily damped mode, and each with many
# segments' degrees of freedom in a record of a few thousand samples.
SEGMENT = 32


@dataclass(frozen=True)
class NoveltyReference:
    """What a healthy record's free-run error is, for one baseline: the statistics a service
    stores beside the model (:meth:`to_document`).

    Attributes
    ----------
    sigma2 : σ̂²₀, the healthy free-run error variance [response units²].
    band_power : P̂₀(b), b = 1 … ⌈M/2⌉ − 1, the healthy error's mean periodogram in each band
        [response units²] (band b centred on b/M of the sampling rate).
    segment : M, the samples of a segment.
    n_segments : K₀, the healthy segments averaged.
    n_samples : n₀, the healthy error samples pooled; ``n_records`` the healthy records.
    start_up : L, the samples at a record's start left out (its free run's initial outputs).
    radius : the largest root modulus of the baseline's linear part at rest.
    marginal : the linear part does not ring down within ``MAX_START_UP`` samples.
    """

    sigma2: float
    band_power: tuple[float, ...]
    segment: int
    n_segments: int
    n_samples: int
    n_records: int
    start_up: int
    radius: float
    marginal: bool

    @property
    def dof(self) -> float:
        """ν₀ = 2K₀, each band power's degrees of freedom."""
        return 2.0 * self.n_segments

    def to_document(self) -> dict[str, Any]:
        document = asdict(self)
        document["band_power"] = list(self.band_power)
        return {"kind": "novelty_reference", "schema_version": DOCUMENT_VERSION, **document}

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> NoveltyReference:
        if not isinstance(document, dict) or document.get("kind") != "novelty_reference":
            raise InputError("not a novelty reference document")
        if document.get("schema_version") != DOCUMENT_VERSION:
            raise InputError(
                f"novelty reference document has schema version {document.get('schema_version')!r}; "
                f"this narxwatch reads version {DOCUMENT_VERSION}"
            )
        try:
            return cls(
                sigma2=float(document["sigma2"]),
                band_power=tuple(float(v) for v in document["band_power"]),
                segment=int(document["segment"]),
                n_segments=int(document["n_segments"]),
                n_samples=int(document["n_samples"]),
                n_records=int(document["n_records"]),
                start_up=int(document["start_up"]),
                radius=float(document["radius"]),
                marginal=bool(document["marginal"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"novelty reference document: missing or invalid field ({exc})") from None


@dataclass(frozen=True)
class NoveltyVerdict:
    """One record judged against a healthy baseline (module docstring for the equations).

    Attributes
    ----------
    status : ``healthy`` or ``anomaly``.
    free_run : ``settled``; ``marginal`` (the baseline's free run does not ring down: the
        design rate does not hold); ``diverged`` (the free run left every bound at sample
        ``diverged_at``: an anomaly, its statistics infinite).
    statistic : F = s²/r; ``threshold`` F_{1−α}(ν, ν₀); ``p_value`` P(F(ν, ν₀) > F).
    severity : s²/σ̂²₀, the record's simulation-error variance over the healthy one.
    sigma2 : s² [response units²]; ``expected_sigma2`` r, a healthy record's expected s².
    dof, reference_dof : ν = 2K and ν₀ = 2K₀, a band power's degrees of freedom.
    n_samples : the record's samples; ``used_samples`` n = N − L those judged.
    band : the band of the largest ratio, its centre as a fraction of the sampling rate
        (None for a diverged run).
    """

    status: Status
    free_run: FreeRunState
    statistic: float
    threshold: float
    p_value: float
    severity: float
    sigma2: float
    expected_sigma2: float
    dof: float
    reference_dof: float
    alpha: float
    n_samples: int
    used_samples: int
    diverged_at: int | None
    band: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible; infinite figures (a diverged free run) as None."""
        return {
            key: (None if isinstance(value, float) and not np.isfinite(value) else value)
            for key, value in asdict(self).items()
        }


def novelty_reference(
    model: NARX,
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    *,
    folds: int = 2,
    segment: int = SEGMENT,
) -> NoveltyReference:
    """The healthy free-run error of ``model`` on the healthy ``records`` (x, y) it was trained
    on: σ̂²₀ and the band powers P̂₀(b) over segments of ``segment`` samples (module docstring).

    The errors are taken out of sample: the records are cut into ``folds`` groups, and each
    group's errors come from ``model``'s terms refitted by output error (from the estimated
    start) on the other groups, started from ``model``'s θ. In sample, the fit has already shaped
    its error to its own records' noise: the reference comes out low, and every later healthy
    record looks a little worse than the records the baseline learnt from. With one fold (or one
    record) the errors are ``model``'s own.

    Refused when a free run diverges on one of the healthy records: the baseline cannot then say
    what a healthy record's simulation error is.
    """
    if not (isinstance(segment, int) and segment >= 4):
        raise InputError(f"the segment must be a whole number of at least 4 samples, got {segment}")
    radius, _, marginal = start_up_of(model)
    L = model.max_lag
    checked = checked_records(records, L + max(MIN_SAMPLES, segment), degree=max_degree(model.terms))
    groups = min(int(folds), len(checked))
    if groups < 1:
        raise InputError(f"folds must be a whole number of at least 1, got {folds}")
    errors = []
    for fold in range(groups):
        held = list(range(fold, len(checked), groups))
        fitted = model
        if groups > 1:
            rest = [record for index, record in enumerate(checked) if index not in held]
            fitted = fit_output_error(model, rest, start_from="estimated").model
        for index in held:
            error = estimated_start_error(fitted, *checked[index])
            if not np.all(np.isfinite(error)):
                raise InputError(
                    f"the baseline's free run diverges on its healthy record {index + 1}: it cannot serve "
                    "as the reference of a simulation error (fit it by output error, or choose a lower order)"
                )
            errors.append(error[L:])
    n0 = sum(e.size for e in errors)
    sigma2 = float(sum(float(e @ e) for e in errors)) / n0
    if not sigma2 > 0:
        raise InputError(
            "the baseline reproduces its healthy records exactly: there is no error to test against"
        )
    periodograms = np.concatenate([_periodograms(e, segment) for e in errors])
    return NoveltyReference(
        sigma2=sigma2,
        band_power=tuple(float(v) for v in periodograms.mean(axis=0)),
        segment=segment,
        n_segments=periodograms.shape[0],
        n_samples=n0,
        n_records=len(errors),
        start_up=L,
        radius=radius,
        marginal=marginal,
    )


def judge_record(
    model: NARX, reference: NoveltyReference, x: ArrayLike, y: ArrayLike, *, alpha: float = 0.05
) -> NoveltyVerdict:
    """Judge one record (x: excitation, y: response) against the healthy baseline ``model`` and
    its ``reference`` at false-alarm rate ``alpha`` (module docstring)."""
    if not 0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    L, M = reference.start_up, reference.segment
    xa, ya = checked_record(x, y, L + max(MIN_SAMPLES, M), degree=max_degree(model.terms))
    n = ya.size - L
    bands = len(reference.band_power)
    nu, nu0 = 2.0 * (n // M), reference.dof
    # Šidák: each band at 1 − (1 − α)^(1/B), so that all B stay below theirs with probability 1 − α.
    threshold = float(special.fdtri(nu, nu0, (1 - alpha) ** (1 / bands)))
    free_run: FreeRunState = "marginal" if reference.marginal else "settled"
    error = estimated_start_error(model, xa, ya)
    if not np.all(np.isfinite(error)):
        diverged_at = int(np.argmax(~np.isfinite(error)))
        return NoveltyVerdict(
            "anomaly", "diverged", np.inf, threshold, 0.0, np.inf, np.inf, reference.sigma2,
            nu, nu0, alpha, ya.size, n, diverged_at, None,
        )  # fmt: skip
    tail = error[L:]
    ratios = _periodograms(tail, M).mean(axis=0) / np.asarray(reference.band_power)
    worst = int(np.argmax(ratios))
    statistic = float(ratios[worst])
    sigma2 = float(tail @ tail) / n
    return NoveltyVerdict(
        status="anomaly" if statistic > threshold else "healthy",
        free_run=free_run,
        statistic=statistic,
        threshold=threshold,
        p_value=float(-np.expm1(bands * np.log1p(-special.fdtrc(nu, nu0, statistic)))),
        severity=sigma2 / reference.sigma2,
        sigma2=sigma2,
        expected_sigma2=reference.sigma2,
        dof=nu,
        reference_dof=nu0,
        alpha=alpha,
        n_samples=ya.size,
        used_samples=n,
        diverged_at=None,
        band=(worst + 1) / M,
    )


def start_up_of(model: NARX) -> tuple[float, int, bool]:
    """(radius, S, marginal) of ``model``'s linear part at rest (module docstring).

    The linear part is y[t] = Σ_k a_k·y[t−k] from the plain lags of y and dy (dy[t−k] =
    y[t−k] − y[t−k−1]); the other terms vanish at rest or to first order about it. With
    companion matrix A and a start error of unit variance on each initial output, what is left
    of it at sample t has variance ‖e₁ᵀAᵗ‖²: S is the first t after which the sum of these
    falls below ``START_UP_SHARE``, at least the model's longest lag L.
    """
    L = model.max_lag
    a = _linear_part(model)
    if not a.size or not np.any(a):
        return 0.0, L, False
    R = a.size
    companion = np.zeros((R, R))
    companion[0] = a
    companion[1:, :-1] = np.eye(R - 1)
    radius = float(np.max(np.abs(np.linalg.eigvals(companion))))
    if radius >= 1.0:
        return radius, L, True
    # Σ_{s≥t} ‖e₁ᵀAˢ‖² = e₁ᵀAᵗ·P·(Aᵗ)ᵀe₁ with P the solution of P = I + A·P·Aᵀ (discrete Lyapunov).
    gram = solve_discrete_lyapunov(companion, np.eye(R))
    row = np.zeros(R)
    row[0] = 1.0
    for t in range(MAX_START_UP):
        if float(row @ gram @ row) < START_UP_SHARE:
            return radius, max(t, L), False
        row = row @ companion
    return radius, L, True


def _linear_part(model: NARX) -> np.ndarray:
    """a_1 … a_R of the plain lags of y and dy in ``model`` (R = L + 1 for dy's second sample)."""
    a = np.zeros(model.max_lag + 1)
    for term, value in zip(model.terms, model.theta, strict=True):
        if len(term.factors) != 1:
            continue
        (factor,) = term.factors
        if factor.power != 1 or factor.function != "" or factor.signal not in ("y", "dy"):
            continue
        a[factor.lag - 1] += value
        if factor.signal == "dy":
            a[factor.lag] -= value
    return np.trim_zeros(a, "b")


def _periodograms(error: np.ndarray, segment: int) -> np.ndarray:
    """(K, M/2 − 1): the periodogram |Σ_t ε[t]·e^{−2πibt/M}|²/M of each of the K whole
    segments of M samples, at the bands b = 1 … ⌈M/2⌉ − 1 (neither 0 nor the Nyquist band, whose
    periodograms have one degree of freedom, not two)."""
    K = error.size // segment
    spectra = np.fft.rfft(error[: K * segment].reshape(K, segment), axis=1)
    return np.abs(spectra[:, 1 : (segment + 1) // 2]) ** 2 / segment
