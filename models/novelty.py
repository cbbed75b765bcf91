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

The statistic: does the excitation explain the error? A change of the structure's linear
dynamics adds (G_record − G_baseline)·x to the error, a filtered copy of the measured excitation.
To first order in the change of θ that copy lies in the span of the free run's sensitivities
J = ∂ŷ/∂θ, column i the term's regressor φ_i along the run through the linear part 1/A(q):
ε = J·β + noise, and a healthy record has β = 0 but for the baseline's own estimation error.
The test is the regression of the error on J (a matched filter for every change the model class
can express), so it gathers the fault's whole coherent difference, where a spectrum of the
error alone sees only its excess power over the noise's.

- whitening: an AR(Q) filter w(q) = 1 − Σ c_k q⁻ᵏ fitted by least squares to the healthy
  records' errors (out of sample: each from ``model``'s terms refitted on the other records);
  the error, J and the start's responses S (:class:`models.output_error.EstimatedStart`) of a
  record are all passed through it, so that the regression's residual is near white and the
  F distribution below exact (generalised least squares);
- ẽ and J̃ are projected off S̃ (the start is a nuisance, estimated with the record);
- the directions: the healthy records' projected, whitened sensitivities stacked, J̃₀, give
  the baseline's information J̃₀ᵀJ̃₀ = V·Σ²·Vᵀ (singular values of the scaled columns); the
  r directions whose singular value exceeds ``RANK_TOLERANCE`` of the largest form
  D = V_r·Σ_r⁻¹, so that the baseline's estimation error in u = P·θ, P = Σ_r·V_rᵀ (D's left
  inverse in the information metric, P·D = I), would have covariance σ²·I were the baseline
  its generalised least-squares estimate;
- the baseline's error covariance σ²·C: it is not that estimate. It minimises the unwhitened
  free-run error, and with noise on the measured force the error −G·n_x is coloured by the
  structure's resonances, so by Gauss–Markov its covariance is σ²·C with C ⪰ I, and the gap
  grows with that colour. C is estimated from the healthy records themselves by the
  jackknife of the out-of-sample refits above: with g folds and their refits u₍₋ⱼ₎ = P·θ₍₋ⱼ₎,

      Ĉ_J = (g − 1)/g · Σ_j (u₍₋ⱼ₎ − ū)(u₍₋ⱼ₎ − ū)ᵀ / σ̂²,

  σ̂² the healthy records' whitened residual variance (the σ² the theory is in). The jackknife
  is a sandwich estimate: it sees what each record's actual error does to θ, whatever its
  colour or source. With g − 1 degrees of freedom, often fewer than r, its small eigenvalues
  are noise below the bound, so C is its nearest matrix (Frobenius) that the bound allows,
  C = I + (Ĉ_J − I)₊ (eigenvalues below 1 raised to 1): positive definite, never below the
  theory, and where a fold's refit strays along one direction, only that direction widens.
  With one fold there are no refits, and C = I;
- a record: K = J̃·D (n × r), g = Kᵀẽ, G = KᵀK; the record's estimate û = G⁻¹g of the change has
  covariance σ²·G⁻¹ about the baseline's error, itself σ²·C; so under a healthy record
  û ~ N(0, σ²·(G⁻¹ + C)) and

      T = ûᵀ(G⁻¹ + C)⁻¹û / (r·s²) = gᵀ(G + G·C·G)⁻¹g / (r·s²) ~ F(r, n − R − r),

  s² = (ẽᵀẽ − gᵀG⁻¹g)/(n − R − r) the record's residual variance, n its whitened samples and R
  the start's columns. A record is an ``anomaly`` when T exceeds F_{1−α}(r, n − R − r). The
  record's own s² scales the statistic, so it holds at any excitation level as long as the
  baseline is at the noise floor; the C in (G⁻¹ + C) keeps the rate for records as long as or
  longer than the training ones, where the baseline's own error would otherwise be found.
- severity: s²_ε/σ̂²₀, s²_ε = mean ε²[t], t = L … N−1, σ̂²₀ the healthy records' (out of
  sample): how many times a healthy record's simulation-error variance the record's is; 1 when
  healthy, whatever the record's length, so a person can trend it. It also moves for changes
  the excitation does not explain (the sensor's noise, say), which T does not test.

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
import scipy
from numpy.typing import ArrayLike
from scipy import special
from scipy.linalg import solve_discrete_lyapunov

from models.errors import InputError
from models.narx import NARX
from models.output_error import EstimatedStart, estimated_start_error, fit_output_error
from models.signals import checked_record, checked_records
from models.terms import max_degree, regressor_matrix

Status = Literal["healthy", "anomaly"]
FreeRunState = Literal["settled", "marginal", "diverged"]
DOCUMENT_VERSION = 4
# Deployed databases hold version-3 references, which have no covariance C.
READABLE_VERSIONS = (3, DOCUMENT_VERSION)
# What is left of a start error after the start-up, in all, as a share of one sample's variance.
START_UP_SHARE = 1e-2
# The longest start-up a baseline may need before it counts as marginal.
MAX_START_UP = 50_000
# Error samples a record needs after its initial outputs, at least, for its statistic.
MIN_SAMPLES = 100
# The most folds the reference's refits cut the healthy records into (module docstring): one a
# record up to this many, so that a training costs at most this many more output-error fits.
MAX_FOLDS = 10
# Q, the whitening filter's order: the healthy error of a baseline at its noise floor is near
# white, and what colour is left is short.
WHITENING_ORDER = 10
# Directions of θ the healthy records determine worse than this, relative to the best (a
# singular value of the scaled sensitivities), are left out: a fast-sampled model's autoregressive
# sensitivities are nearly collinear, and a change along what they cannot tell apart moves the
# response by less than the rounding of the others.
RANK_TOLERANCE = 1e-6


@dataclass(frozen=True)
class NoveltyReference:
    """What a healthy record's free-run error is, for one baseline: the statistics a service
    stores beside the model (:meth:`to_document`).

    Attributes
    ----------
    sigma2 : σ̂²₀, the healthy free-run error variance [response units²].
    whitening : c_1 … c_Q of the whitening filter w(q) = 1 − Σ c_k q⁻ᵏ.
    directions : D (p × r), the directions of θ a record's sensitivities are tested along,
        scaled so that the baseline's estimation error along them has covariance σ²·I in theory.
    covariance : C (r × r), the baseline's estimation error along D over σ², as its healthy
        records show it (:func:`novelty_reference`); I where they cannot (one fold, or a
        version-3 document).
    n_samples : n₀, the healthy error samples pooled; ``n_records`` the healthy records.
    start_up : L, the samples at a record's start left out (its free run's initial outputs).
    radius : the largest root modulus of the baseline's linear part at rest.
    marginal : the linear part does not ring down within ``MAX_START_UP`` samples.
    """

    sigma2: float
    whitening: tuple[float, ...]
    directions: tuple[tuple[float, ...], ...]
    covariance: tuple[tuple[float, ...], ...]
    n_samples: int
    n_records: int
    start_up: int
    radius: float
    marginal: bool

    @property
    def rank(self) -> int:
        """r, the directions tested: the statistic's numerator degrees of freedom."""
        return len(self.directions[0]) if self.directions else 0

    def to_document(self) -> dict[str, Any]:
        document = asdict(self)
        document["whitening"] = list(self.whitening)
        document["directions"] = [list(row) for row in self.directions]
        document["covariance"] = [list(row) for row in self.covariance]
        return {"kind": "novelty_reference", "schema_version": DOCUMENT_VERSION, **document}

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> NoveltyReference:
        if not isinstance(document, dict) or document.get("kind") != "novelty_reference":
            raise InputError("not a novelty reference document")
        version = document.get("schema_version")
        if version not in READABLE_VERSIONS:
            raise InputError(
                f"novelty reference document has schema version {version!r}; this narxwatch reads "
                f"versions {', '.join(str(v) for v in READABLE_VERSIONS)}"
            )
        try:
            directions = _rows(document["directions"])
            rank = len(directions[0]) if directions else 0
            # Version 3 was written before C was estimated: its baselines keep the theory's C = I.
            covariance = _rows(np.eye(rank) if version == 3 else document["covariance"])
            if len(covariance) != rank or any(len(row) != rank for row in covariance):
                raise ValueError(f"covariance is not {rank} × {rank}, as the directions are")
            return cls(
                sigma2=float(document["sigma2"]),
                whitening=tuple(float(v) for v in document["whitening"]),
                directions=directions,
                covariance=covariance,
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
    statistic : T; ``threshold`` F_{1−α}(r, ν); ``p_value`` P(F(r, ν) > T).
    severity : s²_ε/σ̂²₀, the record's simulation-error variance over the healthy one.
    sigma2 : s²_ε [response units²]; ``expected_sigma2`` σ̂²₀, a healthy record's.
    dof, residual_dof : r and ν = n − R − r, the statistic's degrees of freedom.
    n_samples : the record's samples; ``used_samples`` N − L those judged.
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
    residual_dof: float
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
    model: NARX,
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    *,
    folds: int | None = None,
) -> NoveltyReference:
    """The healthy free-run error of ``model`` on the healthy ``records`` (x, y) it was trained
    on: σ̂²₀, the whitening filter and the directions D (module docstring).

    The errors are taken out of sample: the records are cut into ``folds`` groups (by default
    one a record, up to ``MAX_FOLDS``), and each group's errors come from ``model``'s terms
    refitted by output error (from the estimated start) on the other groups, started from
    ``model``'s θ. In sample, the fit has already shaped its error to its own records' noise:
    σ̂²₀ comes out low. The same refits are the jackknife that estimates the baseline's error
    covariance C. With one fold (or one record) the errors are ``model``'s own, and C = I. The
    directions are ``model``'s sensitivities on all the records.

    Refused when a free run diverges on one of the healthy records: the baseline cannot then say
    what a healthy record's simulation error is.
    """
    radius, _, marginal = start_up_of(model)
    L = model.max_lag
    checked = checked_records(records, L + MIN_SAMPLES, degree=max_degree(model.terms))
    groups = min(MAX_FOLDS if folds is None else int(folds), len(checked))
    if groups < 1:
        raise InputError(f"folds must be a whole number of at least 1, got {folds}")
    errors, refits = [], []
    for fold in range(groups):
        held = list(range(fold, len(checked), groups))
        fitted = model
        if groups > 1:
            rest = [record for index, record in enumerate(checked) if index not in held]
            fitted = fit_output_error(model, rest, start_from="estimated").model
            refits.append(fitted.theta)
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
    whitening = _whitening_filter(errors, WHITENING_ORDER)
    regressions = [
        _regression(model, whitening, x, y, estimated_start_error(model, x, y)) for x, y in checked
    ]
    sensitivities = np.vstack([J for _, J in regressions])
    scale = np.linalg.norm(sensitivities, axis=0)
    scale[scale == 0] = 1.0
    _, singular, vt = np.linalg.svd(sensitivities / scale, full_matrices=False)
    kept = singular > RANK_TOLERANCE * singular[0]
    directions = (vt[kept].T / singular[kept]) / scale[:, None]
    covariance = np.eye(directions.shape[1])
    if len(refits) > 1:
        # u = Σ_r·V_rᵀ·(scale ⊙ θ), the left inverse of D in the baseline's information metric.
        coordinates = singular[kept, None] * vt[kept] * scale
        noise = _pooled_residual_variance([(e, J @ directions) for e, J in regressions])
        covariance = _error_covariance(np.asarray(refits) @ coordinates.T, noise)
    return NoveltyReference(
        sigma2=sigma2,
        whitening=tuple(float(v) for v in whitening),
        directions=_rows(directions),
        covariance=_rows(covariance),
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
    its ``reference`` at false-alarm rate ``alpha`` (module docstring).

    Examples
    --------
    A baseline trained on four healthy records judges a healthy record and one whose pole has
    fallen by a fifth:

    >>> import numpy as np
    >>> from scipy.signal import lfilter
    >>> from models.narx import fit_narx
    >>> def record(k, seed):  # y[t] = 0.5·(1 − k/100)·y[t-1] + x[t-1] + e[t]
    ...     x, e = np.random.default_rng(seed).standard_normal((2, 2000))
    ...     return x, lfilter([1.0], [1.0, -0.5 * (1 - k / 100)], np.r_[0.0, x[:-1]] + 0.05 * e)
    >>> training = [record(0.0, seed) for seed in range(10, 14)]
    >>> baseline = fit_narx(training, ["y[t-1]", "x[t-1]"])
    >>> reference = novelty_reference(baseline, training)
    >>> judge_record(baseline, reference, *record(0.0, 20)).status
    'healthy'
    >>> judge_record(baseline, reference, *record(20.0, 21)).status
    'anomaly'
    """
    if not 0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    L, Q, r = reference.start_up, len(reference.whitening), reference.rank
    xa, ya = checked_for_judgement(model, reference, x, y)
    used = ya.size - L
    nu = float(used - Q - _linear_part(model).size - r)
    threshold = float(special.fdtri(r, nu, 1 - alpha))
    free_run: FreeRunState = "marginal" if reference.marginal else "settled"
    run_error = estimated_start_error(model, xa, ya)
    if not np.all(np.isfinite(run_error)):
        diverged_at = int(np.argmax(~np.isfinite(run_error)))
        return NoveltyVerdict(
            "anomaly", "diverged", np.inf, threshold, 0.0, np.inf, np.inf, reference.sigma2,
            r, nu, alpha, ya.size, used, diverged_at,
        )  # fmt: skip
    error, sensitivities = _regression(model, np.asarray(reference.whitening), xa, ya, run_error)
    K = sensitivities @ np.asarray(reference.directions)
    g, G = K.T @ error, K.T @ K
    s2 = _residual_sum(error, g, G) / nu
    statistic = float(g @ np.linalg.solve(G + G @ np.asarray(reference.covariance) @ G, g)) / (r * s2)
    tail = run_error[L:]
    sigma2 = float(tail @ tail) / used
    return NoveltyVerdict(
        status="anomaly" if statistic > threshold else "healthy",
        free_run=free_run,
        statistic=statistic,
        threshold=threshold,
        p_value=float(special.fdtrc(r, nu, statistic)),
        severity=sigma2 / reference.sigma2,
        sigma2=sigma2,
        expected_sigma2=reference.sigma2,
        dof=float(r),
        residual_dof=nu,
        alpha=alpha,
        n_samples=ya.size,
        used_samples=used,
        diverged_at=None,
    )


def checked_for_judgement(
    model: NARX, reference: NoveltyReference, x: ArrayLike, y: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) as float64 vectors fit to be judged by :func:`judge_record`: ``MIN_SAMPLES`` after
    the free run's initial outputs, and no value so large that the model's terms overflow. A
    service that queues a judgement checks a record with this before storing it, so that the
    queued judgement cannot fail on what the upload could have refused."""
    return checked_record(x, y, reference.start_up + MIN_SAMPLES, degree=max_degree(model.terms))


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


def _residual_sum(error: np.ndarray, g: np.ndarray, G: np.ndarray) -> float:
    """ẽᵀẽ − gᵀG⁻¹g: what of a record's whitened error its sensitivities along D do not explain."""
    return float(error @ error) - float(g @ np.linalg.solve(G, g))


def _pooled_residual_variance(regressions: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """σ̂², the whitened error's variance the sensitivities K leave, pooled over the healthy
    records' (ẽ, K): the σ² the theory's covariance σ²·I of the baseline's error is in."""
    residual = sum(_residual_sum(e, K.T @ e, K.T @ K) for e, K in regressions)
    return residual / sum(e.size - K.shape[1] for e, K in regressions)


def _error_covariance(refits: np.ndarray, noise: float) -> np.ndarray:
    """C = I + (Ĉ_J − I)₊ from the folds' refits u₍₋ⱼ₎ (rows, in the coordinates of D) and σ̂²
    (module docstring)."""
    groups = refits.shape[0]
    spread = refits - refits.mean(axis=0)
    jackknife = (groups - 1) / groups * (spread.T @ spread) / noise
    values, vectors = np.linalg.eigh(jackknife)
    return np.eye(values.size) + (vectors * np.maximum(values - 1.0, 0.0)) @ vectors.T


def _rows(matrix: Iterable[Iterable[float]]) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in matrix)


def _whitening_filter(errors: list[np.ndarray], order: int) -> np.ndarray:
    """c_1 … c_Q of the AR(Q) model e[t] = Σ c_k·e[t−k] + w[t] fitted by least squares to the
    healthy ``errors`` pooled."""
    lagged = [np.column_stack([e[order - k : e.size - k] for k in range(1, order + 1)]) for e in errors]
    targets = [e[order:] for e in errors]
    return np.linalg.lstsq(np.vstack(lagged), np.concatenate(targets), rcond=None)[0]


def _regression(
    model: NARX, whitening: np.ndarray, x: np.ndarray, y: np.ndarray, error: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(ẽ, J̃) of one record whose free-run ``error`` from the estimated start settles: the error
    and the run's sensitivities to θ from sample L on, whitened by w(q) (their first Q samples
    dropped) and projected off the start's whitened responses S̃ (module docstring)."""
    L, Q = model.max_lag, whitening.size
    start = EstimatedStart.of(model.terms, model.theta, y.size).responses[: y.size - L]
    w = np.concatenate(([1.0], -whitening))

    def whitened(series: np.ndarray) -> np.ndarray:
        return scipy.signal.lfilter(w, [1.0], series, axis=0)[Q:]

    S = whitened(start)
    regressors = regressor_matrix(model.terms, x, y - error)[0]
    # ∂ŷ/∂θ_i = φ_i / A(q): the regressor along the run through the linear part, from rest (what
    # the start would add, S spans).
    J = scipy.signal.lfilter([1.0], np.concatenate(([1.0], -_linear_part(model))), regressors, axis=0)
    projected = np.column_stack([whitened(error[L:]), whitened(J)])
    projected -= S @ np.linalg.lstsq(S, projected, rcond=None)[0]
    return projected[:, 0], projected[:, 1:]
