"""Polynomial NARX models: estimation, prediction and free-run simulation.

The model (SPEC §3) is

    y[t] = φ[t]ᵀ θ + e[t],

with φ[t] a vector of monomials of lagged y and x (see :mod:`models.terms`), θ estimated by
ordinary least squares and e[t] the one-step-ahead prediction error.

A model may have output limits (low, high), where its output saturates, in one of two ways:

- "state": the system's own output is held there — a tank that overflows — so the free run clips
  each ŷ[t] before it feeds the samples after it, y[t] = clip(φ[t]ᵀθ, low, high);
- "sensor": the sensor's range ends there, the system goes on beyond it, so the free run is the
  unclipped recursion with its reported output clipped.

Its one-step predictions are clipped too. Its fit leaves out the equations whose target lies on a
limit (there φ[t]ᵀθ is only known to lie beyond it) and, for a sensor, those reading a clipped
sample (it is not the system's output).

A model may be ``rectified``: its sensor reads the magnitude |z| of the output z its recursion runs
on, as a pulse counter reads a speed whatever its direction (Wigren & Schoukens's coupled electric
drives). Its free run is the recursion on z with |z| reported, started from the measured outputs
taken as z (the positive branch: a reading does not say its sign), and its one-step predictions
are |φ[t]ᵀθ|. Least squares cannot tell the signs the readings dropped: its fit is the recursion's
on the readings, a start for output error (:mod:`models.output_error`), which fits what the
sensor reads.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from models.errors import InputError
from models.regression import least_squares
from models.signals import checked_record, checked_records
from models.simulation import FreeRun
from models.terms import (
    OverTerms,
    Term,
    max_degree,
    max_lag,
    parse_terms,
    regressor_matrix,
    stacked_regressors,
)

DOCUMENT_VERSION = 1
Saturation = Literal["state", "sensor"]


def z_quantile(level: float) -> float:
    """Two-sided standard-normal quantile z_{(1+level)/2}, e.g. 1.96 for 0.95."""
    return float(special.ndtri(0.5 + level / 2))


@dataclass(frozen=True)
class NARX(OverTerms):
    """An estimated (or theoretical) NARX model.

    Attributes
    ----------
    terms : the regressors, in the order of ``theta``.
    theta : parameter estimates, in the physical units of the signals.
    covariance : parameter covariance σ̂²(ΦᵀΦ)⁻¹ (zeros for a theoretical model).
    sigma2 : residual variance σ̂² of the estimation data.
    n_obs : number of equations (rows of Φ) used for estimation.
    output_limits : (low, high) the output saturates at (±inf for a side without), or None;
        ``saturation`` says whether the state or the sensor saturates there.
    rectified : the sensor reads the magnitude of the recursion's output (module docstring).
    """

    terms: tuple[Term, ...]
    theta: np.ndarray
    covariance: np.ndarray
    sigma2: float = 0.0
    n_obs: int = 0
    output_limits: tuple[float, float] | None = None
    saturation: Saturation = "state"
    rectified: bool = False

    @property
    def reads_state(self) -> bool:
        """Whether what the model reports is its recursion's output itself: not where a sensor
        clips it or reads its magnitude."""
        return (self.output_limits is None or self.saturation == "state") and not self.rectified

    def standard_errors(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def intervals(self, level: float = 0.95) -> np.ndarray:
        """Interval estimates θ̂ ± z·se, one row [low, high] per term."""
        half = z_quantile(level) * self.standard_errors()
        return np.column_stack([self.theta - half, self.theta + half])

    def predict(self, x: ArrayLike, y: ArrayLike, t0: int = 0) -> np.ndarray:
        """One-step-ahead predictions ŷ[t] = φ[t]ᵀθ for t = L … N−1 (L = ``max_lag``).

        ``t0`` is the sample index of the first sample in the time base of sinusoidal terms
        (the estimation record's first sample is 0).
        """
        xa, ya = checked_record(x, y, self.max_lag + 1)
        Phi, _ = regressor_matrix(self.terms, xa, ya, t0=t0)
        return self._limited(Phi @ self.theta)

    def residuals(self, x: ArrayLike, y: ArrayLike, t0: int = 0) -> np.ndarray:
        """One-step-ahead prediction errors e[t] = y[t] − ŷ[t] for t = L … N−1."""
        xa, ya = checked_record(x, y, self.max_lag + 1)
        Phi, target = regressor_matrix(self.terms, xa, ya, t0=t0)
        return target - self._limited(Phi @ self.theta)

    def _limited(self, output: np.ndarray) -> np.ndarray:
        output = np.abs(output) if self.rectified else output
        return output if self.output_limits is None else np.clip(output, *self.output_limits)

    def simulate(self, x: ArrayLike, y_initial: ArrayLike, t0: int = 0) -> np.ndarray:
        """Free-run simulation driven by x, started from the first L samples of ``y_initial``.

        Returns the simulated output for every sample (the first L are the initial
        conditions). A model that diverges yields NaN from the sample where it blew up on.
        ``t0`` as for :meth:`predict`.
        """
        L = self.max_lag
        xa = np.asarray(x, dtype=np.float64)
        y0 = np.asarray(y_initial, dtype=np.float64)[:L]
        if y0.size < L:
            raise InputError(f"free-run simulation needs {L} initial output samples, got {y0.size}")
        return self.run_free(FreeRun.build(self.terms, xa, t0), y0)

    def run_free(self, run: FreeRun, y_initial: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """The free run prepared in ``run`` (for these terms) with this model's limits, and its
        parameters or ``theta``: a state saturates inside the recursion, a sensor clips what
        it reports, or reads its magnitude."""
        theta = self.theta if theta is None else theta
        if self.output_limits is None or self.saturation == "state":
            output = run.run(theta, y_initial, self.output_limits)
            return np.abs(output) if self.rectified else output
        return self._limited(run.run(theta, y_initial))

    def to_document(self) -> dict[str, Any]:
        """A JSON-compatible, versioned description from which :meth:`from_document` rebuilds it.

        Output limits appear only when the model has them (a side without a limit as null), and
        ``rectified`` only when it is, so the documents of models without them are those of
        earlier versions."""
        document: dict[str, Any] = {
            "kind": "narx",
            "schema_version": DOCUMENT_VERSION,
            "terms": self.term_names,
            "theta": self.theta.tolist(),
            "covariance": self.covariance.tolist(),
            "sigma2": self.sigma2,
            "n_obs": self.n_obs,
        }
        if self.output_limits is not None:
            document["output_limits"] = [v if np.isfinite(v) else None for v in self.output_limits]
            document["saturation"] = self.saturation
        if self.rectified:
            document["rectified"] = True
        return document

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> NARX:
        check_document(document, "narx")
        terms = parse_terms(document["terms"])
        theta = np.asarray(document["theta"], dtype=np.float64)
        covariance = np.asarray(document["covariance"], dtype=np.float64)
        if theta.shape != (len(terms),) or covariance.shape != (len(terms), len(terms)):
            raise InputError("model document: theta and covariance do not match the terms")
        limits = document.get("output_limits")
        saturation = document.get("saturation", "state")
        if saturation not in get_args(Saturation):
            raise InputError(f"model document: saturation is 'state' or 'sensor', not {saturation!r}")
        rectified = document.get("rectified", False)
        if not isinstance(rectified, bool):
            raise InputError(f"model document: rectified is true or false, not {rectified!r}")
        return cls(
            terms,
            theta,
            covariance,
            float(document["sigma2"]),
            int(document["n_obs"]),
            None if limits is None else checked_limits(limits),
            saturation,
            rectified,
        )


def checked_limits(limits: Sequence[float | None]) -> tuple[float, float]:
    """Output limits (low, high) from two numbers, None for a side without one; refused unless
    low < high."""
    try:
        low, high = (
            default if v is None else float(v) for v, default in zip(limits, (-np.inf, np.inf), strict=True)
        )
    except (TypeError, ValueError):
        raise InputError(f"output limits are two numbers [low, high] or null, got {limits!r}") from None
    if np.isnan(low) or np.isnan(high) or not low < high:
        raise InputError(f"output limits need low < high, got {limits!r}")
    return low, high


def fit_narx(
    records: Iterable[tuple[ArrayLike, ArrayLike]],
    terms: Sequence[str | Term],
    t0: int | Sequence[int] = 0,
    output_limits: tuple[float, float] | None = None,
    saturation: Saturation = "state",
) -> NARX:
    """Estimate a NARX model by OLS from one or more records.

    Each record contributes its own equations t = L … N−1, so lags never reach across the
    boundary between two records. Sinusoidal terms count time from sample ``t0`` = 0 of each
    record, unless ``t0`` says the records start later in that time base (one index for all, or
    one a record). With ``output_limits`` the model saturates there (its ``saturation`` says
    how) and the equations :func:`fitted_rows` leaves out are not used.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> x = rng.standard_normal(2000)
    >>> y = np.zeros(2000)
    >>> for t in range(2, 2000):
    ...     y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + x[t - 1] + 0.01 * rng.standard_normal()
    >>> model = fit_narx([(x, y)], ["y[t-1]", "y[t-2]", "x[t-1]"])
    >>> np.round(model.theta, 2)
    array([ 1.5, -0.7,  1. ])
    """
    parsed = parse_terms(terms)
    L = max_lag(parsed)
    checked = checked_records(records, L + len(parsed) + 1, degree=max_degree(parsed))
    Phi, target, _ = stacked_regressors(parsed, checked, L, t0)
    if output_limits is not None:
        kept = np.concatenate([fitted_rows(y, L, output_limits, saturation) for _, y in checked])
        if kept.sum() <= len(parsed):
            raise InputError(
                f"only {int(kept.sum())} equations lie clear of the output limits {output_limits}; "
                f"{len(parsed)} terms need more"
            )
        Phi, target = Phi[kept], target[kept]
    fit = least_squares(Phi, target, [t.name for t in parsed])
    return NARX(parsed, fit.theta, fit.covariance, fit.sigma2, len(target), output_limits, saturation)


def sensor_limits(model: NARX) -> tuple[float, float] | None:
    """The limits ``model``'s sensor clips its readings to (None where it reads its state)."""
    return model.output_limits if model.saturation == "sensor" else None


def run_start(y: np.ndarray, lag: int, limits: tuple[float, float] | None) -> int:
    """Where a free run over readings ``y`` starts from measured outputs: at ``lag``, or with a
    sensor's ``limits`` at the first t ≥ ``lag`` whose readings y[t−lag … t−1] all lie clear of
    them. A clipped reading is not the system's output, and a run started from it starts from a
    state the system was not in: on a lightly damped structure the wrong start rings through the
    whole run and hides what the model is. ``lag`` where no such t is."""
    if limits is None or lag == 0:
        return lag
    on = (y <= limits[0]) | (y >= limits[1])
    clear = np.flatnonzero(np.convolve(on, np.ones(lag), "valid")[: max(len(y) - lag, 0)] == 0)
    return lag + int(clear[0]) if clear.size else lag


def fitted_rows(y: np.ndarray, lag: int, limits: tuple[float, float], saturation: Saturation) -> np.ndarray:
    """Which equations t = lag … N−1 a saturating model is fitted on: those whose target is off
    the limits, and for a saturating sensor those whose lagged outputs are off them too."""
    on = (y <= limits[0]) | (y >= limits[1])
    reach = lag if saturation == "sensor" else 0
    touched = np.zeros(len(y) - lag, dtype=bool)
    for k in range(reach + 1):
        touched |= on[lag - k : len(y) - k]
    return ~touched


def check_document(document: dict[str, Any], kind: str) -> None:
    """Refuse a document of another kind or schema version, saying which."""
    if not isinstance(document, dict) or document.get("kind") != kind:
        raise InputError(f"not a {kind} model document")
    version = document.get("schema_version")
    if version != DOCUMENT_VERSION:
        raise InputError(
            f"{kind} model document has schema version {version!r}; this narxwatch reads "
            f"version {DOCUMENT_VERSION}"
        )
