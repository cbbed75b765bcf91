"""The exact discrete-time NARX of the forward-difference 2-DOF model (SPEC §2).

Writing the discretised equations with the forward shift q,

    A1(q)·x1 = F + k2·x2,        k2·x1 = A2(q)·x2 + k3·x2³,

with A1(q) = m1/Ts²·(q−1)² + c1/Ts·(q−1) + k1 + k2 and A2(q) = m2/Ts²·(q−1)² + c2/Ts·(q−1) + k2,
and eliminating x1 gives  [A1·A2 − k2²](q)·y + k3·A1(q)·y³ = k2·F.  Dividing by the leading
coefficient m1·m2/Ts⁴ and shifting back by four samples:

    y[t] = Σ_{i=1..4} a_i·y[t−i] + Σ_{i=2..4} c_i·y³[t−i] + b1·x[t−4].
"""

from __future__ import annotations

import numpy as np

from models.basis import FunctionalBasis
from models.fnarx import FNARX
from models.narx import NARX
from models.terms import parse_terms
from simulator.physics import FaultMode, PhysicalParameters, characteristic_polynomial

EXACT_TERMS = parse_terms(
    ["y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]", "y[t-2]^3", "y[t-3]^3", "y[t-4]^3", "x[t-4]"]
)


def exact_coefficients(params: PhysicalParameters) -> np.ndarray:
    """Coefficients of :data:`EXACT_TERMS` for a parameter set (metres and newtons)."""
    p = params
    poly = characteristic_polynomial(p)  # q⁴ … q⁰
    lead = poly[0]
    a1_shift = np.array(
        [p.m1 / p.ts**2, -2 * p.m1 / p.ts**2 + p.c1 / p.ts, p.m1 / p.ts**2 - p.c1 / p.ts + p.k1 + p.k2]
    )
    autoregressive = -poly[1:] / lead
    cubic = -p.k3 * a1_shift / lead
    exogenous = p.k2 / lead
    return np.concatenate([autoregressive, cubic, [exogenous]])


def exact_narx(params: PhysicalParameters) -> NARX:
    """The noise-free NARX model of the structure, with zero covariance."""
    n = len(EXACT_TERMS)
    return NARX(EXACT_TERMS, exact_coefficients(params), np.zeros((n, n)))


def exact_trajectories(params: PhysicalParameters, mode: FaultMode, k: np.ndarray) -> np.ndarray:
    """Theoretical coefficients over fault magnitudes k (rows), the paper's Figure 4 dashes."""
    return np.array([exact_coefficients(params.with_fault(mode, float(kk))) for kk in np.atleast_1d(k)])


def exact_fault_mode(params: PhysicalParameters, mode: FaultMode, k_min: float, k_max: float) -> FNARX:
    """The exact fault-mode model: coefficients are affine in a stiffness, so p = 2 is exact."""
    basis = FunctionalBasis("chebyshev2", 2, k_min, k_max)
    ends = np.array([k_min, k_max])
    G = basis.values(ends)  # rows g(k_min), g(k_max)
    theta = np.linalg.solve(G, exact_trajectories(params, mode, ends)).T
    n = len(EXACT_TERMS)
    return FNARX(mode, EXACT_TERMS, basis, theta, np.zeros((2 * n, 2 * n)), ends, np.zeros(2), 0)
