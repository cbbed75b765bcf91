"""Functional NARX (FNARX) fault-mode models (SPEC §4).

Each NARX coefficient is a function of the fault magnitude k on a functional basis,

    θ_i(k) = Σ_j θ_ij·G_j(k),    y_k[t] = [φ_k[t] ⊗ g(k)]ᵀ·θ + e_k[t],

and θ = vec(θ_ij) (row-major: term i, then basis function j) is estimated by OLS over the
M experiments stacked. σ²(k) is the mean squared residual of each experiment.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from models.basis import BasisFamily, FunctionalBasis
from models.errors import InputError
from models.narx import NARX, check_document, z_quantile
from models.regression import least_squares
from models.signals import checked_record
from models.terms import OverTerms, Term, max_degree, max_lag, parse_terms, regressor_matrix

Experiment = tuple[ArrayLike, ArrayLike, float]


@dataclass(frozen=True)
class CoefficientTrajectories:
    """Coefficients θ_i(k) over a grid of magnitudes with their pointwise interval estimates.

    ``values``, ``low`` and ``high`` have shape (len(k), n_terms).
    """

    k: np.ndarray
    term_names: list[str]
    values: np.ndarray
    low: np.ndarray
    high: np.ndarray


@dataclass(frozen=True)
class FNARX(OverTerms):
    """A fault-mode model: NARX coefficients as functions of the fault magnitude k (percent).

    Attributes
    ----------
    name : the fault mode, e.g. ``"k2"``.
    terms : the regressors φ.
    basis : the functional basis g(k).
    theta : projection coefficients θ_ij, shape (n_terms, p).
    covariance : covariance of vec(θ) (row-major), shape (n_terms·p, n_terms·p).
    experiment_k, experiment_sigma2 : magnitude and residual variance of each experiment.
    n_obs : number of stacked equations used for estimation.
    """

    name: str
    terms: tuple[Term, ...]
    basis: FunctionalBasis
    theta: np.ndarray
    covariance: np.ndarray
    experiment_k: np.ndarray
    experiment_sigma2: np.ndarray
    n_obs: int

    def check_magnitude(self, k: float) -> float:
        if not np.isfinite(k) or not self.basis.contains(k):
            raise InputError(
                f"fault magnitude {k} is outside the range [{self.basis.k_min}, {self.basis.k_max}] "
                f"of fault-mode model {self.name!r}"
            )
        return float(k)

    def coefficients(self, k: float) -> np.ndarray:
        """θ(k) = Θ·g(k), the NARX coefficients at magnitude k."""
        return self.theta @ self.basis.values(self.check_magnitude(k))

    def coefficient_covariance(self, k: float) -> np.ndarray:
        """Cov θ(k) = (I ⊗ g(k))ᵀ · Cov vec(θ) · (I ⊗ g(k))."""
        g = self.basis.values(self.check_magnitude(k))
        selector = np.kron(np.eye(len(self.terms)), g[:, None])
        return selector.T @ self.covariance @ selector

    def narx_at(self, k: float) -> NARX:
        """The NARX model of the structure with fault magnitude k."""
        return NARX(self.terms, self.coefficients(k), self.coefficient_covariance(k), self.sigma2_at(k), 0)

    def sigma2_at(self, k: float) -> float:
        """σ²(k), interpolated linearly between the experiments."""
        order = np.argsort(self.experiment_k)
        return float(np.interp(k, self.experiment_k[order], self.experiment_sigma2[order]))

    def trajectories(self, k: ArrayLike, level: float = 0.95) -> CoefficientTrajectories:
        grid = np.asarray(k, dtype=np.float64)
        values = np.array([self.coefficients(kk) for kk in grid])
        se = np.array([np.sqrt(np.diag(self.coefficient_covariance(kk))) for kk in grid])
        half = z_quantile(level) * se
        return CoefficientTrajectories(grid, self.term_names, values, values - half, values + half)

    def to_document(self) -> dict[str, Any]:
        return {
            "kind": "fnarx",
            "schema_version": 1,
            "name": self.name,
            "terms": self.term_names,
            "basis": self.basis.to_document(),
            "theta": self.theta.tolist(),
            "covariance": self.covariance.tolist(),
            "experiment_k": self.experiment_k.tolist(),
            "experiment_sigma2": self.experiment_sigma2.tolist(),
            "n_obs": self.n_obs,
        }

    @classmethod
    def from_document(cls, document: dict[str, Any]) -> FNARX:
        check_document(document, "fnarx")
        terms = parse_terms(document["terms"])
        basis = FunctionalBasis.from_document(document["basis"])
        theta = np.asarray(document["theta"], dtype=np.float64)
        covariance = np.asarray(document["covariance"], dtype=np.float64)
        size = len(terms) * basis.size
        if theta.shape != (len(terms), basis.size) or covariance.shape != (size, size):
            raise InputError("fault-mode model document: theta and covariance do not match the terms")
        return cls(
            str(document["name"]),
            terms,
            basis,
            theta,
            covariance,
            np.asarray(document["experiment_k"], dtype=np.float64),
            np.asarray(document["experiment_sigma2"], dtype=np.float64),
            int(document["n_obs"]),
        )


def fit_fnarx(
    experiments: Iterable[Experiment],
    terms: Sequence[str | Term],
    *,
    name: str,
    family: BasisFamily = "chebyshev2",
    size: int = 2,
    k_range: tuple[float, float] | None = None,
    lag: int | None = None,
) -> FNARX:
    """Estimate a fault-mode model from experiments (x, y, k) by Kronecker-stacked OLS.

    ``size`` is p, the number of basis functions (p = 2, degree 1, is exact for stiffness
    faults). ``k_range`` defaults to the smallest and largest experiment magnitude. Each
    experiment contributes its equations t = ``lag`` … N−1; ``lag`` defaults to the largest
    lag of the terms (structure selection passes its dictionary's, to fit the same equations).

    Examples
    --------
    A first-order structure whose pole falls as k grows, from experiments at 0, 10 and 20 %:

    >>> import numpy as np
    >>> from scipy.signal import lfilter
    >>> def record(k, seed):  # y[t] = 0.5·(1 − k/100)·y[t-1] + x[t-1] + e[t]
    ...     x, e = np.random.default_rng(seed).standard_normal((2, 2000))
    ...     return x, lfilter([1.0], [1.0, -0.5 * (1 - k / 100)], np.r_[0.0, x[:-1]] + 0.05 * e)
    >>> experiments = [(*record(k, seed), k) for seed, k in enumerate((0.0, 10.0, 20.0))]
    >>> mode = fit_fnarx(experiments, ["y[t-1]", "x[t-1]"], name="pole")
    >>> mode.theta.shape, (float(mode.basis.k_min), float(mode.basis.k_max))
    ((2, 2), (0.0, 20.0))
    """
    parsed = parse_terms(terms)
    L = max_lag(parsed) if lag is None else max(lag, max_lag(parsed))
    runs = list(experiments)
    if not runs:
        raise InputError("a fault-mode model needs experiments")
    magnitudes = np.array([float(k) for _, _, k in runs])
    if not np.all(np.isfinite(magnitudes)):
        raise InputError("every experiment needs a finite fault magnitude k")
    k_min, k_max = k_range if k_range is not None else (magnitudes.min(), magnitudes.max())
    if np.unique(magnitudes).size < size:
        raise InputError(
            f"a basis of {size} functions needs experiments at {size} or more distinct magnitudes, "
            f"got {np.unique(magnitudes).size}"
        )
    basis = FunctionalBasis(family, size, float(k_min), float(k_max))
    outside = magnitudes[(magnitudes < basis.k_min) | (magnitudes > basis.k_max)]
    if outside.size:
        raise InputError(f"experiment magnitude {outside[0]} lies outside [{k_min}, {k_max}]")

    blocks, targets, lengths = [], [], []
    for index, (x, y, k) in enumerate(runs):
        xa, ya = checked_record(
            x, y, L + len(parsed) + 1, label=f"experiment {index + 1} (k={k})", degree=max_degree(parsed)
        )
        Phi, target = regressor_matrix(parsed, xa, ya, L)
        g = basis.values(float(k))
        blocks.append((Phi[:, :, None] * g[None, None, :]).reshape(len(target), -1))
        targets.append(target)
        lengths.append(len(target))
    names = [f"{t.name}·G{j + 1}" for t in parsed for j in range(size)]
    fit = least_squares(np.vstack(blocks), np.concatenate(targets), names)
    per_experiment = np.split(fit.residuals, np.cumsum(lengths)[:-1])
    return FNARX(
        name=name,
        terms=parsed,
        basis=basis,
        theta=fit.theta.reshape(len(parsed), size),
        covariance=fit.covariance,
        experiment_k=magnitudes,
        experiment_sigma2=np.array([np.mean(e**2) for e in per_experiment]),
        n_obs=int(sum(lengths)),
    )
