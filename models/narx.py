"""Polynomial NARX models: estimation, prediction and free-run simulation.

The model (SPEC §3) is

    y[t] = φ[t]ᵀ θ + e[t],

with φ[t] a vector of monomials of lagged y and x (see :mod:`models.terms`), θ estimated by
ordinary least squares and e[t] the one-step-ahead prediction error.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from models.errors import InputError
from models.regression import least_squares
from models.signals import checked_record, checked_records
from models.simulation import FreeRun
from models.terms import Term, max_degree, max_lag, parse_terms, regressor_matrix, stacked_regressors

DOCUMENT_VERSION = 1


def z_quantile(level: float) -> float:
    """Two-sided standard-normal quantile z_{(1+level)/2}, e.g. 1.96 for 0.95."""
    return float(special.ndtri(0.5 + level / 2))


@dataclass(frozen=True)
class NARX:
    """An estimated (or theoretical) NARX model.

    Attributes
    ----------
    terms : the regressors, in the order of ``theta``.
    theta : parameter estimates, in the physical units of the signals.
    covariance : parameter covariance σ̂²(ΦᵀΦ)⁻¹ (zeros for a theoretical model).
    sigma2 : residual variance σ̂² of the estimation data.
    n_obs : number of equations (rows of Φ) used for estimation.
    """

    terms: tuple[Term, ...]
    theta: np.ndarray
    covariance: np.ndarray
    sigma2: float = 0.0
    n_obs: int = 0

    @property
    def max_lag(self) -> int:
        return max_lag(self.terms)

    @property
    def term_names(self) -> list[str]:
        return [term.name for term in self.terms]

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
        return Phi @ self.theta

    def residuals(self, x: ArrayLike, y: ArrayLike, t0: int = 0) -> np.ndarray:
        """One-step-ahead prediction errors e[t] = y[t] − ŷ[t] for t = L … N−1."""
        xa, ya = checked_record(x, y, self.max_lag + 1)
        Phi, target = regressor_matrix(self.terms, xa, ya, t0=t0)
        return target - Phi @ self.theta

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
        return FreeRun.build(self.terms, xa, t0).run(self.theta, y0)

    def to_document(self) -> dict[str, Any]:
        """A JSON-compatible, versioned description from which :meth:`from_document` rebuilds it."""
        return {
            "kind": "narx",
            "schema_version": DOCUMENT_VERSION,
            "terms": self.term_names,
            "theta": self.theta.tolist(),
            "covariance": self.covariance.tolist(),
            "sigma2": self.sigma2,
            "n_obs": self.n_obs,
        }

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> NARX:
        check_document(document, "narx")
        terms = parse_terms(document["terms"])
        theta = np.asarray(document["theta"], dtype=np.float64)
        covariance = np.asarray(document["covariance"], dtype=np.float64)
        if theta.shape != (len(terms),) or covariance.shape != (len(terms), len(terms)):
            raise InputError("model document: theta and covariance do not match the terms")
        return cls(terms, theta, covariance, float(document["sigma2"]), int(document["n_obs"]))


def fit_narx(
    records: Iterable[tuple[ArrayLike, ArrayLike]], terms: Sequence[str | Term], t0: int | Sequence[int] = 0
) -> NARX:
    """Estimate a NARX model by OLS from one or more records.

    Each record contributes its own equations t = L … N−1, so lags never reach across the
    boundary between two records. Sinusoidal terms count time from sample ``t0`` = 0 of each
    record, unless ``t0`` says the records start later in that time base (one index for all, or
    one a record).
    """
    parsed = parse_terms(terms)
    L = max_lag(parsed)
    checked = checked_records(records, L + len(parsed) + 1, degree=max_degree(parsed))
    Phi, target, _ = stacked_regressors(parsed, checked, L, t0)
    fit = least_squares(Phi, target, [t.name for t in parsed])
    return NARX(parsed, fit.theta, fit.covariance, fit.sigma2, len(target))


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
