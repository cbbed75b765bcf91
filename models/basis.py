"""Functional bases G_1(k) … G_p(k) on the normalised fault magnitude (SPEC §4).

The magnitude k ∈ [k_min, k_max] is mapped to u = (2k − k_max − k_min)/(k_max − k_min) ∈ [−1, 1].
Each family is held as a p×p matrix C of power-series coefficients, G_j(u) = Σ_i C[j, i]·u^i,
so values and derivatives of every family come from one Vandermonde product.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.polynomial import legendre
from numpy.typing import ArrayLike

from models.errors import InputError

BasisFamily = Literal["chebyshev2", "legendre", "power"]
FAMILIES: tuple[BasisFamily, ...] = ("chebyshev2", "legendre", "power")


def _power_coefficients(family: BasisFamily, size: int) -> np.ndarray:
    if family == "power":
        return np.eye(size)
    if family == "legendre":
        return np.array([np.pad(legendre.leg2poly(row), (0, size))[:size] for row in np.eye(size)])
    # Chebyshev of the second kind: U_0 = 1, U_1 = 2u, U_{n+1} = 2u·U_n − U_{n−1}.
    C = np.zeros((size, size))
    C[0, 0] = 1.0
    for j in range(1, size):
        C[j, 1:] = 2 * C[j - 1, :-1]
        if j > 1:
            C[j] -= C[j - 2]
    return C


@dataclass(frozen=True)
class FunctionalBasis:
    """A basis of ``size`` functions of the fault magnitude over [k_min, k_max] (percent)."""

    family: BasisFamily
    size: int
    k_min: float
    k_max: float

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise InputError(f"unknown basis {self.family!r}; choose one of {', '.join(FAMILIES)}")
        if self.size < 1:
            raise InputError("a functional basis needs at least one function")
        if not self.k_min < self.k_max:
            raise InputError(f"the fault range [{self.k_min}, {self.k_max}] is empty")
        object.__setattr__(self, "_coefficients", _power_coefficients(self.family, self.size))

    @property
    def power_coefficients(self) -> np.ndarray:
        """C with G_j(u) = Σ_i C[j, i]·u^i."""
        return self._coefficients

    @property
    def is_affine(self) -> bool:
        """True when every G_j is at most linear in k, so residuals are affine in k."""
        return self.size <= 2

    def contains(self, k: float) -> bool:
        return self.k_min <= k <= self.k_max

    def normalise(self, k: ArrayLike) -> np.ndarray:
        return (2 * np.asarray(k, dtype=np.float64) - self.k_max - self.k_min) / (self.k_max - self.k_min)

    def values(self, k: ArrayLike) -> np.ndarray:
        """g(k) = [G_1(k) … G_p(k)]; shape (..., p)."""
        return self._powers(k) @ self._coefficients.T

    def derivatives(self, k: ArrayLike) -> np.ndarray:
        """dg/dk, in 1/percent; shape (..., p)."""
        du_dk = 2.0 / (self.k_max - self.k_min)
        # d/du of Σ_i C[j, i]·u^i, written back on the same powers 0 … p−1.
        D = np.zeros_like(self._coefficients)
        D[:, :-1] = self._coefficients[:, 1:] * np.arange(1, self.size)
        return du_dk * (self._powers(k) @ D.T)

    def _powers(self, k: ArrayLike) -> np.ndarray:
        u = self.normalise(k)
        return np.polynomial.polynomial.polyvander(u, self.size - 1).reshape(*u.shape, self.size)

    def to_document(self) -> dict[str, object]:
        return {"family": self.family, "size": self.size, "k_min": self.k_min, "k_max": self.k_max}

    @classmethod
    def from_document(cls, document: dict[str, object]) -> FunctionalBasis:
        return cls(
            str(document["family"]),  # type: ignore[arg-type]
            int(document["size"]),  # type: ignore[arg-type]
            float(document["k_min"]),  # type: ignore[arg-type]
            float(document["k_max"]),  # type: ignore[arg-type]
        )
