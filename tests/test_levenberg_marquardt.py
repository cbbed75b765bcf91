"""MINPACK's Levenberg–Marquardt search (models.levenberg_marquardt) against SciPy's, which runs
the same algorithm, and its QR against LAPACK's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize

from models.levenberg_marquardt import enorm, minimise, qrfac

T = np.linspace(0.0, 10.0, 200)
MEASURED = 3.0 * np.exp(-0.4 * T) * np.cos(2.1 * T + 0.3) + 0.05 * np.random.default_rng(0).normal(
    size=T.size
)


def residuals(p: np.ndarray) -> np.ndarray:
    return p[0] * np.exp(-p[1] * T) * np.cos(p[2] * T + p[3]) - MEASURED


def jacobian(p: np.ndarray) -> np.ndarray:
    decay, phase = np.exp(-p[1] * T), p[2] * T + p[3]
    cos, sin = decay * np.cos(phase), decay * np.sin(phase)
    return np.column_stack([cos, -T * p[0] * cos, -T * p[0] * sin, -p[0] * sin])


@pytest.mark.parametrize(
    ("start", "budget"),
    [
        ((1.0, 0.1, 2.0, 0.0), 30),
        ((2.0, 0.5, 2.2, 0.1), 100),
        ((1.0, 1.0, 1.0, 1.0), 5),
        ((1.0, 1.0, 1.0, 1.0), 200),
    ],
)
def test_the_search_is_scipys_step_for_step(start: tuple[float, ...], budget: int) -> None:
    """Where the Jacobian is well conditioned (no column norm is recomputed) the search is
    least_squares' "lm" to the last bit: the same end, Jacobian, status and evaluations, also
    where the budget ends it (status 0)."""
    x0 = np.array(start)
    scipy = optimize.least_squares(residuals, x0, jac=jacobian, method="lm", x_scale="jac", max_nfev=budget)
    ours = minimise(residuals, jacobian, x0, budget)
    np.testing.assert_array_equal(ours.x, scipy.x)
    np.testing.assert_array_equal(ours.jac, scipy.jac)
    assert (ours.status, ours.nfev) == (scipy.status, scipy.nfev)


def test_the_pivoted_qr_reads_nothing_past_its_matrix_and_is_lapacks() -> None:
    """A last column that repeats another: once that one is pivoted, its remaining norm is
    recomputed, over its own rows only, so that the value stored after the matrix changes
    nothing; |R|'s diagonal is LAPACK's QR of the permuted columns (rank-deficient: the last
    is zero to rounding)."""
    rng = np.random.default_rng(1)
    m, n = 12, 5
    factored = []
    for after in (0.0, 1e300):
        memory = np.empty(m * n + 1)
        memory[-1] = after
        a = memory[: m * n].reshape(n, m).T  # column-major, as MINPACK stores it
        a[:] = rng.normal(size=(m, n)) if not factored else factored[0][0]
        a[:, -1] = a[:, 1]
        original = a.copy()
        ipvt, rdiag, acnorm, work = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n), np.empty(n)
        qrfac(a, ipvt, rdiag, acnorm, work)
        factored.append((original, a.copy(), ipvt.copy(), rdiag.copy()))
    (original, first, ipvt, rdiag), (_, second, ipvt2, rdiag2) = factored
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(ipvt, ipvt2)
    np.testing.assert_array_equal(rdiag, rdiag2)
    lapack = np.abs(np.diag(np.linalg.qr(original[:, ipvt], mode="r")))
    np.testing.assert_allclose(np.abs(rdiag[:-1]), lapack[:-1], rtol=1e-12)
    assert abs(rdiag[-1]) < 1e-12 * abs(rdiag[0]) and lapack[-1] < 1e-12 * lapack[0]


@pytest.mark.parametrize("scale", [1.0, 1e-200, 1e200])
def test_the_norm_neither_overflows_nor_underflows(scale: float) -> None:
    """MINPACK's enorm is ‖x‖₂, also where squaring the components would overflow or vanish."""
    x = np.array([3.0, -4.0, 12.0, 0.0]) * scale
    assert enorm(x) == pytest.approx(13.0 * scale, rel=1e-15)
