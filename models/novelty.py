"""Baseline-only monitoring: is a record unlike the healthy records a baseline was trained on?

A structure brought without fault experiments has a healthy baseline alone, and a record is
judged against it: ``healthy`` or ``anomaly``, at a false-alarm rate α that is designed, not tuned.

Why the simulation error, not the one-step residual. The inspection chain's residual is the
one-step prediction error, white when the noise enters the structure as a force (equation
error). A real sensor adds its noise to what it measures instead, and at a fast sampling rate the
one-step residual is then mostly that noise passed through the model's autoregressive part,
which nearly differences it: coloured, far above the healthy model's σ̂², and insensitive to the
structure (the lagged outputs it predicts from carry the change). The free run ŷ[t] of the
baseline driven by the measured force alone (:mod:`models.simulation`), started from the
record's first L measured outputs, has the error

    ε[t] = y[t] − ŷ[t] = n_y[t] − G·n_x[t] + (G_record − G_baseline)·x[t]   (linear case),

the sensor noise on y, the noise on x through the baseline, and what the structure's change
does to the response: the last is the whole difference a fault makes to the response, not its
shadow in one step.

The statistic (units: the response's squared units, as ratios here, so none):

- reference (:func:`novelty_reference`): the healthy records' free-run errors from sample S on
  (the start-up below), out of sample (each from the baseline's terms fitted on the other
  records), pooled, n₀ samples: σ̂²₀ = Σε²/n₀, and their autocorrelation ρ̂₀(τ), τ = 1 … S;
- a record's mean square s² = mean ε²[t], t = S … N−1 (n = N − S samples), against what a
  healthy record's is expected to be, r = σ̂²₀ + mean_t s[t]ᵀ·Cov θ·s[t], the second term the
  baseline's own estimation error carried by the record's free-run sensitivities
  s[t] = ∂ŷ[t]/∂θ (it grows with the record's excitation level, the noise floor does not);
- the ratio F = s²/r. For a Gaussian series of autocorrelation ρ the variance of a sample
  variance is 2σ⁴κ/n with κ = 1 + 2Σ_{τ≥1} ρ²(τ) (Bartlett), the variance of a χ²_ν/ν with
  ν = n/κ degrees of freedom; so s² ≈ r·χ²_ν/ν, σ̂²₀ ≈ σ²·χ²_{ν₀}/ν₀ with ν₀ = (n₀ − p)/κ
  (Satterthwaite), and F ≈ F(ν, ν₀). A record is an ``anomaly`` when F > F_{1−α}(ν, ν₀):
  one-sided, since a change of the structure adds to the error. ν scales with the record's
  length and ν₀ carries the reference's own uncertainty, so the rate holds for records shorter
  or longer than the training ones, and for other excitation levels as long as the sensor noise
  is a floor (its variance does not grow with the signal) and the baseline is at that floor.
- severity: the ratio s²/σ̂²₀, how many times a healthy record's simulation-error variance
  the record's is; 1 when healthy, whatever the record's length, so a person can trend it.

The start-up S: the free run starts from noisy measured outputs, and the error of that start
rings down through the baseline's own poles. S is the first sample after which what is left of
it, for a start error of the residual's variance on each of the L initial outputs, carries less
than ``START_UP_SHARE`` of one sample's variance in all (computed from the baseline's linear
part at rest, its companion matrix). A baseline whose linear part does not ring down within
``MAX_START_UP`` samples (a root on or outside the unit circle, or too near it) is ``marginal``:
its verdicts say so, for its free-run error is not stationary and the design rate does not hold.
A record whose free run diverges is an ``anomaly`` whose verdict says so (``diverged_at``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy import special
from scipy.linalg import solve_discrete_lyapunov

from models.diagnostics import autocorrelation
from models.errors import InputError
from models.narx import NARX
from models.output_error import fit_output_error
from models.signals import checked_record, checked_records
from models.simulation import FreeRun
from models.terms import max_degree

Status = Literal["healthy", "anomaly"]
FreeRunState = Literal["settled", "marginal", "diverged"]
DOCUMENT_VERSION = 1
# What is left of the free run's start error after the start-up, in all, as a share of one
# sample's variance: a bias of s² far below its standard error (√(2κ/n) ≥ 1/√n).
START_UP_SHARE = 1e-2
# The longest start-up a baseline may need before it counts as marginal.
MAX_START_UP = 50_000
# Residual samples a record needs after the start-up, at least, for its statistic.
MIN_SAMPLES = 100


@dataclass(frozen=True)
class NoveltyReference:
    """What a healthy record's free-run error is, for one baseline: the statistics a service
    stores beside the model (:meth:`to_document`).

    Attributes
    ----------
    sigma2 : σ̂²₀, the healthy free-run error variance [response units²].
    variance_factor : κ = 1 + 2Σρ̂₀²(τ), τ = 1 … ``start_up``: how much the error's colour
        widens a sample variance's spread beside a white series'.
    n_samples : n₀, the healthy error samples pooled; ``n_parameters`` p fitted on them (0
        when they are out of sample).
    n_records : the healthy records.
    start_up : S, the samples at a record's start left out of its statistic.
    radius : the largest root modulus of the baseline's linear part at rest.
    marginal : the linear part does not ring down within ``MAX_START_UP`` samples.
    """

    sigma2: float
    variance_factor: float
    n_samples: int
    n_parameters: int
    n_records: int
    start_up: int
    radius: float
    marginal: bool

    @property
    def dof(self) -> float:
        """ν₀ = (n₀ − p)/κ, the reference's degrees of freedom."""
        return max(self.n_samples - self.n_parameters, 1) / self.variance_factor

    def to_document(self) -> dict[str, Any]:
        return {"kind": "novelty_reference", "schema_version": DOCUMENT_VERSION, **asdict(self)}

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
                variance_factor=float(document["variance_factor"]),
                n_samples=int(document["n_samples"]),
                n_parameters=int(document["n_parameters"]),
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
    dof, reference_dof : ν and ν₀.
    n_samples : the record's samples; ``used_samples`` n = N − S those judged.
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

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible; infinite figures (a diverged free run) as None."""
        return {
            key: (None if isinstance(value, float) and not np.isfinite(value) else value)
            for key, value in asdict(self).items()
        }


def novelty_reference(
    model: NARX, records: Iterable[tuple[ArrayLike, ArrayLike]], *, folds: int = 2
) -> NoveltyReference:
    """The healthy free-run error of ``model`` on the healthy ``records`` (x, y) it was trained
    on: σ̂²₀, κ and the start-up (module docstring).

    The errors are taken out of sample: the records are cut into ``folds`` groups, and each
    group's errors come from ``model``'s terms refitted by output error on the other groups,
    started from ``model``'s θ. In sample, the fit has already shaped its error to its own
    records' noise: the reference comes out low, and every later healthy record looks a little
    worse than the records the baseline learnt from (a few percent of variance, as much as a
    record's own sampling spread). With one fold (or one record) the errors are ``model``'s own
    and σ̂²₀ takes the usual correction n₀/(n₀ − p).

    Refused when a free run diverges on one of the healthy records: the baseline cannot then say
    what a healthy record's simulation error is.
    """
    radius, start_up, marginal = start_up_of(model)
    checked = checked_records(records, start_up + MIN_SAMPLES, degree=max_degree(model.terms))
    groups = min(int(folds), len(checked))
    if groups < 1:
        raise InputError(f"folds must be a whole number of at least 1, got {folds}")
    errors = []
    for fold in range(groups):
        held = list(range(fold, len(checked), groups))
        fitted = model
        if groups > 1:
            rest = [record for index, record in enumerate(checked) if index not in held]
            fitted = fit_output_error(model, rest).model
        for index in held:
            error = _free_run_error(fitted, *checked[index])
            if not np.all(np.isfinite(error)):
                raise InputError(
                    f"the baseline's free run diverges on its healthy record {index + 1}: it cannot serve "
                    "as the reference of a simulation error (fit it by output error, or choose a lower order)"
                )
            errors.append(error[start_up:])
    n0 = sum(e.size for e in errors)
    p = len(model.terms) if groups == 1 else 0
    if n0 <= p:
        raise InputError(f"{n0} healthy error samples cannot carry a reference for {p} parameters")
    sigma2 = float(sum(float(e @ e) for e in errors)) / (n0 - p)
    if not sigma2 > 0:
        raise InputError(
            "the baseline reproduces its healthy records exactly: there is no error to test against"
        )
    lags = max(min(start_up, min(e.size for e in errors) // 4), 1)
    # Pooled autocovariance over the records (the free-run error has no mean when the baseline
    # has none), lags within records.
    covariance = np.zeros(lags + 1)
    for e in errors:
        covariance += autocorrelation(e, lags) * float(e @ e)
    rho = covariance[1:] / covariance[0]
    kappa = float(1.0 + 2.0 * np.sum(rho**2))
    return NoveltyReference(sigma2, kappa, n0, p, len(errors), start_up, radius, marginal)


def judge_record(
    model: NARX, reference: NoveltyReference, x: ArrayLike, y: ArrayLike, *, alpha: float = 0.05
) -> NoveltyVerdict:
    """Judge one record (x: excitation, y: response) against the healthy baseline ``model`` and
    its ``reference`` at false-alarm rate ``alpha`` (module docstring)."""
    if not 0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    S = reference.start_up
    xa, ya = checked_record(x, y, S + MIN_SAMPLES, degree=max_degree(model.terms))
    n = ya.size - S
    free_run: FreeRunState = "marginal" if reference.marginal else "settled"
    run = FreeRun.build(model.terms, xa)
    error = ya - model.run_free(run, ya)
    nu0 = reference.dof
    if not np.all(np.isfinite(error)):
        diverged_at = int(np.argmax(~np.isfinite(error)))
        return NoveltyVerdict(
            "anomaly", "diverged", np.inf, np.inf, 0.0, np.inf, np.inf, reference.sigma2,
            n / reference.variance_factor, nu0, alpha, ya.size, n, diverged_at,
        )  # fmt: skip
    tail = error[S:]
    s = run.run_with_sensitivities(model.theta, ya)[1][S:]
    estimation = float(np.mean(np.einsum("ti,ij,tj->t", s, model.covariance, s)))
    expected = reference.sigma2 + max(estimation, 0.0)
    sigma2 = float(tail @ tail) / n
    nu = n / reference.variance_factor
    statistic = sigma2 / expected
    threshold = float(special.fdtri(nu, nu0, 1 - alpha))
    return NoveltyVerdict(
        status="anomaly" if statistic > threshold else "healthy",
        free_run=free_run,
        statistic=statistic,
        threshold=threshold,
        p_value=float(special.fdtrc(nu, nu0, statistic)),
        severity=sigma2 / reference.sigma2,
        sigma2=sigma2,
        expected_sigma2=expected,
        dof=nu,
        reference_dof=nu0,
        alpha=alpha,
        n_samples=ya.size,
        used_samples=n,
        diverged_at=None,
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


def _free_run_error(model: NARX, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y[t] − ŷ[t] of the free run driven by x from y's first L samples (zero over those)."""
    return y - model.run_free(FreeRun.build(model.terms, x), y)
