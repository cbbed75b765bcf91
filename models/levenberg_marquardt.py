"""MINPACK's Levenberg–Marquardt search (``lmder``: Moré, "The Levenberg–Marquardt algorithm:
implementation and theory", 1978), step for step as ``scipy.optimize.least_squares(method="lm",
x_scale="jac")`` runs it, without reading memory outside its arrays.

SciPy's C translation of MINPACK (1.15 to 1.17) recomputes a column's remaining norm in the
pivoted QR (``qrfac``) over one element too many: for the last column that element lies past
the end of the Jacobian, whatever the heap held there. On an ill-conditioned Jacobian, where
that recomputation happens, the pivoting and so the search's every later step then depend on
the process's allocation history: the same output-error search gave different θ as the first
call of a process and as a later one (SciPy pull request 24323 fixes it in C). Here each
column's norm is over its own rows, as in the Fortran original; where no norm is recomputed
the arithmetic is SciPy's, operation for operation.

A stopgap, not a rival to SciPy: once a SciPy release carries that fix, narxwatch requires it
and calls ``least_squares`` again, and this module goes (its tests compare the two bit for bit,
so the change is checked).

Only what :mod:`models.output_error` asks for is kept: an analytic Jacobian, the variables
scaled by the Jacobian's column norms (MINPACK's mode 1), SciPy's default tolerances.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

EPSILON = float(np.finfo(np.float64).eps)
DWARF = float(np.finfo(np.float64).tiny)
TOLERANCE = 1e-8  # least_squares' ftol, xtol and gtol by default
FACTOR = 100.0  # the initial step bound's factor, MINPACK's recommended value
# MINPACK's termination codes as least_squares reports them (its ``status``); 6–8, a tolerance
# below the machine's precision, which SciPy's defaults keep from happening, as 1–4 would be.
STATUS = {1: 2, 2: 3, 3: 4, 4: 1, 5: 0, 6: 2, 7: 3, 8: 1}
# enorm's bounds between small, intermediate and large components (2^63.5 as SciPy's C has it).
GIANT = math.pow(2.0, 63.5)
SMALL = 0.5 / GIANT


@dataclass(frozen=True)
class Search:
    """Where the search ended: ``x``, the Jacobian there, least_squares' ``status`` and the
    residual evaluations it made (``nfev``)."""

    x: np.ndarray
    jac: np.ndarray
    status: int
    nfev: int


@numba.njit(cache=True, nogil=True)
def _fmax(a: float, b: float) -> float:
    """C's fmax: a NaN loses."""
    if a != a:
        return b
    if b != b:
        return a
    return a if a >= b else b


@numba.njit(cache=True, nogil=True)
def _fmin(a: float, b: float) -> float:
    """C's fmin: a NaN loses."""
    if a != a:
        return b
    if b != b:
        return a
    return a if a <= b else b


@numba.njit(cache=True, nogil=True)
def enorm(x: np.ndarray) -> float:
    """The Euclidean norm of ``x`` without overflow or destructive underflow (MINPACK's enorm):
    small, intermediate and large components summed apart."""
    s1 = s2 = s3 = x1max = x3max = 0.0
    agiant = GIANT / x.size
    for i in range(x.size):
        xabs = abs(x[i])
        if xabs <= SMALL or xabs >= agiant:
            if xabs > SMALL:
                if xabs > x1max:
                    ratio = x1max / xabs
                    s1 = 1.0 + s1 * (ratio * ratio)
                    x1max = xabs
                else:
                    ratio = xabs / x1max
                    s1 += ratio * ratio
            elif xabs > x3max:
                ratio = x3max / xabs
                s3 = 1.0 + s3 * (ratio * ratio)
                x3max = xabs
            elif xabs != 0.0:
                ratio = xabs / x3max
                s3 += ratio * ratio
        else:
            s2 += xabs * xabs
    if s1 != 0.0:
        return x1max * math.sqrt(s1 + (s2 / x1max) / x1max)
    if s2 != 0.0:
        if s2 >= x3max:
            return math.sqrt(s2 * (1.0 + (x3max / s2) * (x3max * s3)))
        return math.sqrt(x3max * ((s2 / x3max) + (x3max * s3)))
    return x3max * math.sqrt(s3)


@numba.njit(cache=True, nogil=True)
def qrfac(a: np.ndarray, ipvt: np.ndarray, rdiag: np.ndarray, acnorm: np.ndarray, wa: np.ndarray) -> None:
    """Householder QR of the (m, n) ``a`` with column pivoting, in place (MINPACK's qrfac):
    R's strict upper triangle and Q's vectors in ``a``, R's diagonal in ``rdiag``, the columns'
    norms in ``acnorm``, the permutation in ``ipvt``. A recomputed norm is over the column's
    own remaining rows (module docstring)."""
    m, n = a.shape
    for j in range(n):
        acnorm[j] = enorm(a[:, j])
        rdiag[j] = acnorm[j]
        wa[j] = rdiag[j]
        ipvt[j] = j
    for j in range(min(m, n)):
        kmax = j
        for k in range(j, n):
            if rdiag[k] > rdiag[kmax]:
                kmax = k
        if kmax != j:
            for i in range(m):
                temp = a[i, j]
                a[i, j] = a[i, kmax]
                a[i, kmax] = temp
            rdiag[kmax] = rdiag[j]
            wa[kmax] = wa[j]
            k = ipvt[j]
            ipvt[j] = ipvt[kmax]
            ipvt[kmax] = k
        ajnorm = enorm(a[j:, j])
        if ajnorm == 0.0:
            rdiag[j] = -ajnorm
            continue
        if a[j, j] < 0.0:
            ajnorm = -ajnorm
        for i in range(j, m):
            a[i, j] /= ajnorm
        a[j, j] += 1.0
        if j == n - 1:
            rdiag[j] = -ajnorm
            continue
        for k in range(j + 1, n):
            total = 0.0
            for i in range(j, m):
                total += a[i, j] * a[i, k]
            temp = total / a[j, j]
            for i in range(j, m):
                a[i, k] -= temp * a[i, j]
            if rdiag[k] != 0.0:
                temp = a[j, k] / rdiag[k]
                rdiag[k] *= math.sqrt(_fmax(0.0, 1.0 - temp * temp))
                ratio = rdiag[k] / wa[k]
                if 0.05 * (ratio * ratio) <= EPSILON:
                    rdiag[k] = enorm(a[j + 1 :, k])
                    wa[k] = rdiag[k]
        rdiag[j] = -ajnorm


@numba.njit(cache=True, nogil=True)
def qrsolv(
    r: np.ndarray,
    ipvt: np.ndarray,
    diag: np.ndarray,
    qtb: np.ndarray,
    x: np.ndarray,
    sdiag: np.ndarray,
    wa: np.ndarray,
) -> None:
    """The least-squares x of R·Pᵀ·x = Qᵀb, D·x = 0 by Givens rotations (MINPACK's qrsolv); S's
    strict upper triangle, transposed, into R's strict lower one, its diagonal into ``sdiag``."""
    n = r.shape[1]
    for j in range(n):
        for i in range(j, n):
            r[i, j] = r[j, i]
        x[j] = r[j, j]
        wa[j] = qtb[j]
    for j in range(n):
        l = ipvt[j]  # noqa: E741 (MINPACK's name)
        if diag[l] != 0.0:
            for k in range(j, n):
                sdiag[k] = 0.0
            sdiag[j] = diag[l]
            qtbpj = 0.0
            for k in range(j, n):
                if sdiag[k] == 0.0:
                    continue
                if abs(r[k, k]) < abs(sdiag[k]):
                    cotan = r[k, k] / sdiag[k]
                    sin = 0.5 / math.sqrt(0.25 + 0.25 * (cotan * cotan))
                    cos = sin * cotan
                else:
                    tan = sdiag[k] / r[k, k]
                    cos = 0.5 / math.sqrt(0.25 + 0.25 * (tan * tan))
                    sin = cos * tan
                r[k, k] *= cos
                r[k, k] += sin * sdiag[k]
                temp = cos * wa[k] + sin * qtbpj
                qtbpj = -sin * wa[k] + cos * qtbpj
                wa[k] = temp
                for i in range(k + 1, n):
                    temp = cos * r[i, k] + sin * sdiag[i]
                    sdiag[i] = -sin * r[i, k] + cos * sdiag[i]
                    r[i, k] = temp
        sdiag[j] = r[j, j]
        r[j, j] = x[j]
    nsing = n
    for j in range(n):
        if sdiag[j] == 0.0 and nsing == n:
            nsing = j
        if nsing < n:
            wa[j] = 0.0
    for k in range(1, nsing + 1):
        j = nsing - k
        total = 0.0
        for i in range(j + 1, nsing):
            total += r[i, j] * wa[i]
        wa[j] = (wa[j] - total) / sdiag[j]
    for j in range(n):
        x[ipvt[j]] = wa[j]


@numba.njit(cache=True, nogil=True)
def lmpar(
    r: np.ndarray,
    ipvt: np.ndarray,
    diag: np.ndarray,
    qtb: np.ndarray,
    delta: float,
    par: float,
    x: np.ndarray,
    sdiag: np.ndarray,
) -> float:
    """The Levenberg–Marquardt parameter for the step bound ``delta`` and its step, into ``x``
    (MINPACK's lmpar); returns the parameter."""
    n = r.shape[1]
    wa1, wa2 = np.empty(n), np.empty(n)
    nsing = n
    for j in range(n):
        wa1[j] = qtb[j]
        if r[j, j] == 0.0 and nsing == n:
            nsing = j
        if nsing < n:
            wa1[j] = 0.0
    for k in range(1, nsing + 1):
        j = nsing - k
        wa1[j] /= r[j, j]
        temp = wa1[j]
        for i in range(j):
            wa1[i] -= r[i, j] * temp
    for j in range(n):
        x[ipvt[j]] = wa1[j]
    for j in range(n):
        wa2[j] = diag[j] * x[j]
    dxnorm = enorm(wa2)
    fp = dxnorm - delta
    if fp <= 0.1 * delta:
        return 0.0
    parl = 0.0
    if nsing == n:
        for j in range(n):
            l = ipvt[j]  # noqa: E741 (MINPACK's name)
            wa1[j] = diag[l] * (wa2[l] / dxnorm)
        for j in range(n):
            total = 0.0
            for i in range(j):
                total += r[i, j] * wa1[i]
            wa1[j] = (wa1[j] - total) / r[j, j]
        temp = enorm(wa1)
        parl = ((fp / delta) / temp) / temp
    for j in range(n):
        total = 0.0
        for i in range(j + 1):
            total += r[i, j] * qtb[i]
        wa1[j] = total / diag[ipvt[j]]
    gnorm = enorm(wa1)
    paru = gnorm / delta
    if paru == 0.0:
        paru = DWARF / _fmin(delta, 0.1)
    par = _fmin(_fmax(par, parl), paru)
    if par == 0.0:
        par = gnorm / dxnorm
    iteration = 0
    while True:
        iteration += 1
        if par == 0.0:
            par = _fmax(DWARF, paru * 0.001)
        temp = math.sqrt(par)
        for j in range(n):
            wa1[j] = temp * diag[j]
        qrsolv(r, ipvt, wa1, qtb, x, sdiag, wa2)
        for j in range(n):
            wa2[j] = diag[j] * x[j]
        dxnorm = enorm(wa2)
        temp = fp
        fp = dxnorm - delta
        if abs(fp) <= 0.1 * delta or (parl == 0.0 and fp <= temp and temp < 0.0) or iteration == 10:
            return par
        for j in range(n):
            l = ipvt[j]  # noqa: E741 (MINPACK's name)
            wa1[j] = diag[l] * (wa2[l] / dxnorm)
        for j in range(n):
            wa1[j] /= sdiag[j]
            temp = wa1[j]
            for i in range(j + 1, n):
                wa1[i] -= r[i, j] * temp
        temp = enorm(wa1)
        parc = ((fp / delta) / temp) / temp
        if fp > 0.0:
            parl = _fmax(parl, par)
        if fp < 0.0:
            paru = _fmin(paru, par)
        par = _fmax(parl, par + parc)


@numba.njit(cache=True, nogil=True)
def _rotated(
    fjac: np.ndarray, fvec: np.ndarray, rdiag: np.ndarray, norms: np.ndarray, ipvt: np.ndarray, fnorm: float
) -> tuple[np.ndarray, float]:
    """Qᵀf's first n components, R's diagonal put back on ``fjac``'s, and the scaled gradient's
    largest component (lmder's loops 90–170)."""
    m, n = fjac.shape
    wa4 = fvec.copy()
    qtf = np.empty(n)
    for j in range(n):
        if fjac[j, j] != 0.0:
            total = 0.0
            for i in range(j, m):
                total += fjac[i, j] * wa4[i]
            temp = -total / fjac[j, j]
            for i in range(j, m):
                wa4[i] += fjac[i, j] * temp
        fjac[j, j] = rdiag[j]
        qtf[j] = wa4[j]
    gnorm = 0.0
    if fnorm != 0.0:
        for j in range(n):
            column = ipvt[j]
            if norms[column] != 0.0:
                total = 0.0
                for i in range(j + 1):
                    total += fjac[i, j] * (qtf[i] / fnorm)
                gnorm = _fmax(gnorm, abs(total / norms[column]))
    return qtf, gnorm


@numba.njit(cache=True, nogil=True)
def _predicted(fjac: np.ndarray, ipvt: np.ndarray, step: np.ndarray) -> np.ndarray:
    """R·Pᵀ·p, whose norm is the linear model's reduction (lmder's loops 220–230)."""
    n = fjac.shape[1]
    out = np.zeros(n)
    for j in range(n):
        temp = step[ipvt[j]]
        for i in range(j + 1):
            out[i] += fjac[i, j] * temp
    return out


@dataclass
class _State:
    """The search's state between its steps (lmder's local variables)."""

    x: np.ndarray
    fvec: np.ndarray
    fnorm: float
    nfev: int
    diag: np.ndarray
    delta: float = 0.0
    xnorm: float = 0.0
    par: float = 0.0
    iteration: int = 1


def minimise(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    max_nfev: int,
) -> Search:
    """min ‖fun(x)‖² from ``x0`` within ``max_nfev`` evaluations of ``fun``, ``jac`` its
    Jacobian: what ``least_squares(fun, x0, jac=jac, method="lm", x_scale="jac",
    max_nfev=max_nfev)`` reports as ``x``, ``jac``, ``status`` and ``nfev``."""
    x = np.array(x0, dtype=float)
    fvec = np.asarray(fun(x.copy()), dtype=float)
    state = _State(x, fvec, enorm(fvec), 1, np.empty(x.size))
    info = 0
    while not info:
        # Column-major, as MINPACK stores it: its loops run down the columns.
        info = _outer(state, fun, np.array(jac(state.x.copy()), dtype=float, order="F"), max_nfev)
    return Search(state.x, np.asarray(jac(state.x.copy()), dtype=float), STATUS[info], state.nfev)


def _outer(state: _State, fun: Callable[[np.ndarray], np.ndarray], fjac: np.ndarray, max_nfev: int) -> int:
    """One Jacobian's steps: factor it, then step until one is taken or the search ends; the
    termination code, 0 to go on."""
    n = state.x.size
    ipvt = np.empty(n, dtype=np.int64)
    rdiag, norms, work = np.empty(n), np.empty(n), np.empty(n)
    qrfac(fjac, ipvt, rdiag, norms, work)
    if state.iteration == 1:
        state.diag = np.where(norms == 0.0, 1.0, norms)
        state.xnorm = enorm(state.diag * state.x)
        state.delta = FACTOR * state.xnorm or FACTOR
    qtf, gnorm = _rotated(fjac, state.fvec, rdiag, norms, ipvt, state.fnorm)
    if gnorm <= TOLERANCE:
        return 4
    state.diag = np.fmax(state.diag, norms)
    while True:
        info, taken = _step(state, fun, fjac, ipvt, qtf, gnorm, max_nfev)
        if info or taken:
            return info


def _step(
    state: _State,
    fun: Callable[[np.ndarray], np.ndarray],
    fjac: np.ndarray,
    ipvt: np.ndarray,
    qtf: np.ndarray,
    gnorm: float,
    max_nfev: int,
) -> tuple[int, bool]:
    """One trial step within the trust region: the termination code (0 to go on) and whether
    the step was taken."""
    n = state.x.size
    step, sdiag = np.empty(n), np.empty(n)
    state.par = lmpar(fjac, ipvt, state.diag, qtf, state.delta, state.par, step, sdiag)
    step = -step
    trial = state.x + step
    pnorm = enorm(state.diag * step)
    if state.iteration == 1:
        state.delta = _fmin(state.delta, pnorm)
    fvec = np.asarray(fun(trial.copy()), dtype=float)
    state.nfev += 1
    fnorm1 = enorm(fvec)
    fnorm = state.fnorm
    actred = 1.0 - (fnorm1 / fnorm) * (fnorm1 / fnorm) if 0.1 * fnorm1 < fnorm else -1.0
    temp1 = enorm(_predicted(fjac, ipvt, step)) / fnorm
    temp2 = (math.sqrt(state.par) * pnorm) / fnorm
    prered = temp1 * temp1 + temp2 * temp2 / 0.5
    dirder = -(temp1 * temp1 + temp2 * temp2)
    ratio = actred / prered if prered != 0.0 else 0.0
    if ratio <= 0.25:
        temp = (0.5 * dirder) / (dirder + 0.5 * actred) if actred < 0.0 else 0.5
        if 0.1 * fnorm1 >= fnorm or temp < 0.1:
            temp = 0.1
        state.delta = temp * _fmin(state.delta, pnorm / 0.1)
        state.par /= temp
    elif state.par == 0.0 or ratio >= 0.75:
        state.delta = pnorm / 0.5
        state.par *= 0.5
    taken = ratio >= 1e-4
    if taken:
        state.x, state.fvec, state.fnorm = trial, fvec, fnorm1
        state.xnorm = enorm(state.diag * trial)
        state.iteration += 1
    return _ended(state, actred, prered, ratio, gnorm, max_nfev), taken


def _ended(state: _State, actred: float, prered: float, ratio: float, gnorm: float, max_nfev: int) -> int:
    """lmder's convergence and termination tests after a step, in its order (a later test's
    code replaces an earlier one's): its code, 0 to go on."""
    reduced = abs(actred) <= TOLERANCE and prered <= TOLERANCE and 0.5 * ratio <= 1.0
    small = state.delta <= TOLERANCE * state.xnorm
    if reduced or small:
        return 3 if reduced and small else 1 if reduced else 2
    info = 5 if state.nfev >= max_nfev else 0
    if abs(actred) <= EPSILON and prered <= EPSILON and 0.5 * ratio <= 1.0:
        info = 6
    if state.delta <= EPSILON * state.xnorm:
        info = 7
    if gnorm <= EPSILON:
        info = 8
    return info
