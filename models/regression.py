"""Ordinary least squares with column scaling, as every model here is estimated.

NARX regressions are badly scaled: the AR block is nearly the binomial (4, −6, 4, −1) and the
exogenous coefficient is ~1e-10 in metres and newtons. Each column is divided by its Euclidean
norm before a QR factorisation, and the estimates and their covariance are reported back in
the physical units of the unscaled problem.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from scipy import linalg
from scipy.linalg import lapack

from models.errors import InputError

# A scaled design whose condition number exceeds this carries no usable information on at
# least one coefficient (double precision keeps ~16 digits; the estimate would keep < 4).
MAX_CONDITION = 1e12
# A map-like callable, workers(function, items), as scipy's optimisers take one: the builtin map,
# or a process pool's, which runs each call in a process of its own (or a thread pool's).
Workers = Callable[[Callable[[Any], Any], Iterable[Any]], Iterable[Any]]
# Singular values below this share of the largest are dependence among the columns, not directions
# of their span (span_basis): their Gram matrix resolves eigenvalues down to ε, singular values
# down to √ε.
SPAN_TOLERANCE = 1e-7


@dataclass(frozen=True)
class LeastSquaresFit:
    """Result of :func:`least_squares`.

    Attributes
    ----------
    theta : estimates θ̂ = (ΦᵀΦ)⁻¹Φᵀy in the units of the columns.
    covariance : σ̂²(ΦᵀΦ)⁻¹, the asymptotic covariance of θ̂.
    sigma2 : σ̂² = mean(e²), the residual variance.
    residuals : e = y − Φθ̂.
    condition : condition number of the column-scaled design.
    """

    theta: np.ndarray
    covariance: np.ndarray
    sigma2: float
    residuals: np.ndarray
    condition: float


def least_squares(
    Phi: np.ndarray, target: np.ndarray, column_names: Sequence[str] | None = None
) -> LeastSquaresFit:
    """Solve min ‖y − Φθ‖² by QR of the column-scaled design.

    Raises :class:`InputError` when a column is identically zero or the columns are linearly
    dependent, naming the columns involved, since a person can act on that (a constant or
    too-short signal, or a term listed in two forms).
    """
    names = list(column_names) if column_names is not None else [f"column {i}" for i in range(Phi.shape[1])]
    Q, R, scale, condition = scaled_qr(Phi, names)
    theta_scaled = linalg.solve_triangular(R, Q.T @ target)
    residuals = target - Phi @ (theta_scaled / scale)
    sigma2 = float(np.mean(residuals**2))
    return LeastSquaresFit(
        theta_scaled / scale, scaled_covariance(R, scale, sigma2), sigma2, residuals, condition
    )


def scaled_qr(Phi: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Q·R = Φ/s, s the columns' Euclidean norms: (Q, R, s, R's condition number), after
    refusing, as :func:`least_squares` does, a design that cannot determine its parameters."""
    n_obs, n_par = Phi.shape
    if n_obs <= n_par:
        raise InputError(
            f"{n_obs} usable samples cannot determine {n_par} parameters: supply a longer record"
        )
    overflowed = [names[i] for i in np.flatnonzero(~np.all(np.isfinite(Phi), axis=0))]
    if overflowed:
        raise InputError(
            f"regressor {', '.join(overflowed)} overflows on these signals: lower its power or scale the data"
        )
    scale = column_norms(Phi)
    zero = [names[i] for i in np.flatnonzero(~(scale > 0))]
    if zero:
        raise InputError(
            f"regressor {', '.join(zero)} is identically zero: the signal it uses is constant "
            "or zero over the record, so its coefficient cannot be estimated"
        )
    Q, R = linalg.qr(divided_columns(Phi, scale), mode="economic", overwrite_a=True, check_finite=False)
    return Q, R, scale, checked_condition(R, names)


def divided_columns(Phi: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Φ/s written column by column (Fortran order), the layout LAPACK factors in: scipy's QR,
    allowed to overwrite it, then copies nothing, where it copies a row-major Φ/s once more
    (65 000 × 44: 76 → 64 ms; the same factors to the last digit)."""
    return np.divide(Phi, scale, out=np.empty(Phi.shape, order="F"))


def column_norms(columns: np.ndarray) -> np.ndarray:
    """Each column's Euclidean norm, the same to the last bit as ``np.linalg.norm(columns,
    axis=0)``. Of a row-major matrix of several columns that norm sums the squares row after row,
    and einsum sums them in that order without writing the squares out first: a third of the
    time (65 000 × 4 or 40 000 × 10, the candidates' and a search's columns). Of a column-major
    matrix or a single column numpy sums each column pairwise, in another order: its norm."""
    if columns.ndim == 2 and columns.shape[1] > 1 and columns.flags.c_contiguous:
        return np.sqrt(np.einsum("ij,ij->j", columns, columns))
    return np.linalg.norm(columns, axis=0)


def checked_condition(R: np.ndarray, names: Sequence[str]) -> float:
    """The condition number of the scaled design whose triangular factor is R; raises
    :class:`InputError` when it is ``MAX_CONDITION`` or more (linearly dependent columns),
    naming the weakest column."""
    condition = float(np.linalg.cond(R))
    if not condition < MAX_CONDITION:
        weakest = names[int(np.argmin(np.abs(np.diag(R))))]
        raise InputError(
            f"the regressors are linearly dependent (condition number {condition:.2g}); "
            f"{weakest} is explained by the others: the excitation is not rich enough "
            "or the structure names a term twice"
        )
    return condition


def scaled_covariance(R: np.ndarray, scale: np.ndarray, sigma2: float) -> np.ndarray:
    """σ²(ΦᵀΦ)⁻¹ in the columns' units, from the triangular factor R of Φ/s."""
    R_inv = linalg.solve_triangular(R, np.eye(R.shape[0]))
    return sigma2 * (R_inv @ R_inv.T) / np.outer(scale, scale)


def orthogonal_part(columns: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Columns minus their projection on the orthonormal Q, by Gram–Schmidt. Once loses
    orthogonality when a column lies nearly in Q's span; a column that kept less than 1/√2 of its
    norm is projected again, and twice is enough (Kahan–Parlett; Giraud, Langou & Rozložník,
    *Comput. Math. Appl.* 50, 2005). On Silverbox's loop three columns in four need only once."""
    # Squared norms by einsum, which reads the columns once where np.linalg.norm squares a copy
    # of them first (a quarter of the time): only the test below reads them.
    squared = np.einsum("ij,ij->j", columns, columns)
    # Qᵀ·columns as (columnsᵀ·Q)ᵀ: for a few columns OpenBLAS takes a quarter less time this way
    # round with a Q in Fortran order, as scipy's QR makes it (2.7 against 3.5 ms for four columns
    # of Silverbox's 65 000 × 51), half with one in C order; Silverbox's report is the same to
    # the last bit.
    columns = columns - Q @ (columns.T @ Q).T
    again = np.einsum("ij,ij->j", columns, columns) < squared / 2
    if np.any(again):
        columns[:, again] -= Q @ (columns[:, again].T @ Q).T
    return columns


def span_basis(columns: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the span of the tall ``columns`` (empty for no columns), from the
    eigenvectors of their Gram matrix, twice: the first pass leaves the basis orthogonal to
    within κ²·ε, the second to rounding (the pattern of CholeskyQR2: Fukaya, Kannan, Nakatsukasa,
    Yamamoto & Yanagisawa, *SIAM J. Sci. Comput.* 42, 2020), in a third of the time of a
    Householder QR and its Q (37 against 101 ms on 40 columns of 65 000 rows). Directions whose
    singular value is below ``SPAN_TOLERANCE`` of the largest are left out: a column that repeats
    others, say, which the Gram matrix cannot resolve below that."""
    if columns.shape[1] == 0:
        return columns
    basis = columns / column_norms(columns)
    for _ in range(2):
        values, vectors = linalg.eigh(basis.T @ basis)
        kept = values > values[-1] * SPAN_TOLERANCE**2
        basis = basis @ (vectors[:, kept] / np.sqrt(values[kept]))
    return basis


def triangular_factor(A: np.ndarray, block: int = 2048, threads: Workers = map) -> np.ndarray:
    """The triangular factor R of A = QR for a tall A (rows ≫ columns), by Householder QR of
    blocks of ``block`` rows and then of their stacked factors (TSQR: Demmel, Grigori, Hoemmen &
    Langou, *SIAM J. Sci. Comput.* 34, 2012). As stable as one QR of A, and each block stays in
    cache where one QR of a 65 000-row matrix streams it from memory once per column: 3–4 times
    faster on the output-error Jacobians. The blocks are factored by ``threads``, a map over
    threads of this process (:data:`Workers`): LAPACK lets go of the interpreter while it works,
    so two threads take 23 ms where one takes 40 on Silverbox's 65 000 × 52, to the same bits.
    R's rows are determined up to sign."""
    factors = list(
        threads(_householder_factor, [A[first : first + block] for first in range(0, A.shape[0], block)])
    )
    return _householder_factor(np.vstack(factors)) if len(factors) > 1 else factors[0]


def _householder_factor(A: np.ndarray) -> np.ndarray:
    """R of A = QR by LAPACK's Householder QR (``dgeqrf``, as ``np.linalg.qr(A, mode="r")``, which
    holds the interpreter throughout)."""
    factored, *_ = lapack.dgeqrf(A)  # its status reports only illegal arguments
    return np.triu(factored[: min(A.shape)])


@numba.njit(cache=True, nogil=True)
def subtract_outer(W: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    """W −= w·vᵀ in place, each entry as numpy's ``W -= np.outer(w, v)`` makes it (the product
    rounded, then the difference), in one pass over W where numpy writes the outer product out
    first and reads it back (:func:`models.scoring._greedy` deflates a family's columns so at
    each step, tens of columns of 65 000 rows on Silverbox)."""
    rows, columns = W.shape
    for i in range(rows):
        for j in range(columns):
            W[i, j] -= w[i] * v[j]
