"""Alarm rules across records: a CUSUM with a computed design, persistence, severity.

One record's verdict is a test at level α; four records a day make α = 0.05 about ten false
alarms a week. An alarm rule looks at a structure's verdicts in order and answers "act now":

- *sequential* — a two-sided CUSUM (Page 1954) on each fault mode's standardised estimate
  z_i = (k̂_i − k₀)/σ̂_k,i (σ units; z ~ N(0, 1) on a healthy structure, k₀ = 0 the healthy state):

      S⁺_i = max(0, S⁺_{i−1} + z_i − r),   S⁻_i = max(0, S⁻_{i−1} − z_i − r),   S^±_0 = 0,

  alarming at the first record i where S⁺_i > h or S⁻_i > h. The reference r = δ/2 (σ units)
  makes it the optimal test for a step of δ σ (Moustakides 1986); the decision interval h is
  computed from the target in-control average run length (ARL, in records), never tuned by hand.
  The z of one structure are not independent: the fault-mode model's own estimation error (a
  share c of σ̂_k², a few per cent) is the same in every record, so the design averages the
  false-alarm rate over it (``in_control_arl``).
- *persistence* — k of the last m verdicts faulty or unknown;
- *severity* — a verdict's interval for k lies wholly beyond a magnitude threshold.

The ARL of the one-sided upper chart, started at u ∈ [0, h], with z ~ N(μ, 1), solves the
integral equation (Page 1954; Goel & Wu 1971)

    L(u) = 1 + L(0)·Φ(r − μ − u) + ∫₀ʰ L(x)·φ(x − u + r − μ) dx,

a Fredholm equation of the second kind with a smooth Gaussian kernel, solved here by the
Nyström method on Gauss–Legendre nodes (error far below 10⁻⁶ relative at 64 nodes for h < 10;
``tests/test_alarms_design.py`` compares it with a Monte Carlo of the chart and with Siegmund's
approximation). The lower chart on z is the upper chart on −z, so ARL₋(μ) = ARL₊(−μ). The
two-sided chart's ARL follows from the two one-sided ones:

    1/ARL = 1/ARL₊ + 1/ARL₋,

exactly for r ≥ 0 and a zero start (Van Dobben de Bruyn 1968; Lucas & Crosier 1982): while
both sides are positive their sum falls by 2r every record, so it never exceeds h, and a side
alarms only with the other at zero — the state the other side's run started from — whence the
renewal argument gives the relation. The design assumes the chart restarts at zero after each
alarm, so that the alarms of a healthy structure are a renewal process with mean spacing ARL.

References
----------
Page, E. S. (1954). Continuous inspection schemes. Biometrika 41, 100–115.
Goel, A. L., Wu, S. M. (1971). Determination of A.R.L. and a contour nomogram for CUSUM charts
to control normal mean. Technometrics 13, 221–230.
Brook, D., Evans, D. A. (1972). An approach to the probability distribution of CUSUM run
length. Biometrika 59, 539–549 (the same equation as a Markov chain on a grid of states).
Siegmund, D. (1985). Sequential Analysis. Springer, chapter II.
Van Dobben de Bruyn, C. S. (1968). Cumulative Sum Tests: Theory and Practice. Griffin.
Lucas, J. M., Crosier, R. B. (1982). Fast initial response for CUSUM quality-control schemes.
Technometrics 24, 199–205.
Moustakides, G. V. (1986). Optimal stopping times for detecting changes in distributions.
Annals of Statistics 14, 1379–1387.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import scipy
from numpy.typing import ArrayLike

from models.errors import InputError

QUADRATURE_NODES = 64  # at least; more for h > 16
NEVER = 1e10  # records: ARLs beyond are reported as inf (the integral equation cannot resolve them)
MAX_THRESHOLD = 100.0  # σ units: the largest decision interval the design searches
COMMON_NODES = 24
RECORDS_PER_DAY = 4.0  # the record rate the defaults are designed for when none is stated
# σ units: the CUSUM is tuned to a step of two standard errors of k̂. A smaller reference (δ = 1) is
# optimal for 1σ steps only if the verdicts' z are independent; with the few per cent of σ̂k² that
# the fault-mode model's error makes common to all records (``in_control_arl``), it needs h ≈ 18
# instead of 4.4 for the same false-alarm rate and is slower at every step from 1σ up.
DESIGN_SHIFT = 2.0
PERSISTENCE_K = 3
PERSISTENCE_M = 5


@dataclass(frozen=True)
class CusumDesign:
    """A two-sided CUSUM on standardised estimates z ~ N(0, 1) in control.

    ``reference`` (r) and ``threshold`` (h) are in σ units; the run lengths are in records.
    """

    reference: float
    threshold: float
    arl_in_control: float
    arl_at_shift: float
    common_share: float = 0.0


@dataclass(frozen=True)
class CusumPath:
    """The two CUSUM statistics after each observation and the first alarm.

    ``drift_start`` is the index after the last record at which the alarming side was zero
    before ``alarm_at`` (0 when it never was): the change-point estimate of the CUSUM (Page 1954),
    the first record of the run of evidence that ended in the alarm.
    """

    upper: np.ndarray
    lower: np.ndarray
    alarm_at: int | None
    drift_start: int | None


@dataclass(frozen=True)
class CusumChart:
    """A CUSUM run as a service runs it: restarted from zero after each alarm.

    ``statistic`` is max(S⁺_i, S⁻_i) after each observation; ``alarms`` the indices at which the
    chart signalled, each with its drift start (:class:`CusumPath`) in ``drift_starts``.
    """

    statistic: np.ndarray
    alarms: tuple[int, ...]
    drift_starts: tuple[int, ...]


@dataclass(frozen=True)
class AlarmRules:
    """The rules a structure's verdicts are judged by, for one record rate.

    ``cusum`` is per fault mode; its in-control ARL is the structure's target spread over the
    ``modes`` charts (their false alarms add up at most, Boole's inequality).
    """

    cusum: CusumDesign
    persistence_k: int
    persistence_m: int
    records_per_day: float
    modes: int


def one_sided_arl(threshold: float, reference: float, mean: float) -> float:
    """Zero-start ARL (records) of the upper chart S_i = max(0, S_{i−1} + z_i − r), z ~ N(μ, 1).

    Parameters
    ----------
    threshold : h, σ units (the chart alarms when S > h).
    reference : r, σ units.
    mean : μ, the mean of z in σ units.

    Returns
    -------
    L(0), the solution of the integral equation in the module docstring by Gauss–Legendre
    Nyström (``QUADRATURE_NODES`` nodes, four per σ of h beyond); inf beyond ``NEVER`` records.

    Examples
    --------
    >>> round(one_sided_arl(5.0, 0.5, 0.0), 1), round(one_sided_arl(5.0, 0.5, 1.0), 2)  # tables: 930, 10.4
    (930.9, 10.38)
    """
    if not threshold > 0:
        raise InputError(f"the decision interval must be positive; got h = {threshold}")
    return float(_arl_nystrom(float(threshold), float(reference), float(mean)))


def _arl_nystrom(h: float, r: float, mu: float) -> float:
    # The kernel is a unit Gaussian: four nodes per σ of interval keep the rule exact to ~10⁻⁹.
    nodes, weights = _gauss_legendre(max(QUADRATURE_NODES, int(np.ceil(4 * h))))
    x = 0.5 * h * (nodes + 1.0)
    w = 0.5 * h * weights
    # Unknowns: L at the nodes, and L(0) (the chart's start and its reset state).
    u = np.concatenate([x, [0.0]])
    shift = r - mu
    A = np.empty((u.size, u.size))
    A[:, :-1] = -scipy.stats.norm.pdf(x[None, :] - u[:, None] + shift) * w[None, :]
    A[:, -1] = -scipy.stats.norm.cdf(shift - u)  # the step to or below zero resets the chart
    A[np.arange(u.size), np.arange(u.size)] += 1.0
    # I − K is singular to working precision once L(0) nears 1/eps, or exactly (the solve then
    # refuses): such a chart never alarms in any service's lifetime, and its rate 1/ARL is zero to
    # the precision anything here needs.
    try:
        L = np.linalg.solve(A, np.ones(u.size))[-1]
    except np.linalg.LinAlgError:
        return np.inf
    return L if np.isfinite(L) and 0 < L < NEVER else np.inf


@cache
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(n)


def two_sided_arl(threshold: float, reference: float, mean: float) -> float:
    """Zero-start ARL (records) of the two-sided chart: 1/ARL = 1/ARL₊(μ) + 1/ARL₊(−μ).

    Examples
    --------
    >>> round(two_sided_arl(4.0, 0.5, 0.0), 1)  # half the one-sided run length in control
    167.7
    """
    rate = 1.0 / one_sided_arl(threshold, reference, mean) + 1.0 / one_sided_arl(threshold, reference, -mean)
    return 1.0 / rate if rate > 0 else np.inf


def siegmund_arl(threshold: float, reference: float, mean: float) -> float:
    """Siegmund's approximation to the one-sided ARL, for checking the integral equation only.

    With Δ = μ − r and b = h + 1.166 (the mean overshoot of a Gaussian walk, 2·0.583):
    ARL ≈ (exp(−2Δb) + 2Δb − 1)/(2Δ²), and b² when Δ = 0 (Siegmund 1985, ch. II). Accurate to a
    few per cent for the h and r used here.
    """
    delta = mean - reference
    b = threshold + 1.166
    if abs(delta) < 1e-12:
        return b * b
    return float((np.exp(-2.0 * delta * b) + 2.0 * delta * b - 1.0) / (2.0 * delta * delta))


def in_control_arl(threshold: float, reference: float, common_share: float = 0.0) -> float:
    """In-control ARL (records) of the two-sided chart when part of z's variance is common to all records.

    A structure's z_i = (k̂_i − k₀)/σ̂_k,i share the fault-mode model's own estimation error: the
    delta-method part of σ̂_k² (``models.inspection``), a fraction c of it, is the same offset in
    every record inspected with that model. In control, then, z_i = β + √(1 − c)·ε_i with β ~ N(0, c)
    fixed for the structure and ε_i ~ N(0, 1) independent — still N(0, 1) for one record, but a
    structure whose β is large alarms far more often. The false-alarm *rate* averaged over
    structures (over β) is E_β[1/ARL(h | β)], so the in-control ARL quoted here is

        ARL = 1 / E_β[1/ARL(h/ρ, r/ρ; β/ρ)],   ρ = √(1 − c),

    (the chart on z/ρ has unit variance), with E_β by Gauss–Hermite quadrature on ``COMMON_NODES``
    nodes. c = 0 gives ``two_sided_arl(h, r, 0)``.

    Examples
    --------
    >>> round(in_control_arl(6.0, 0.5, 0.0)), round(in_control_arl(6.0, 0.5, 0.06))
    (1277, 244)
    """
    if not 0.0 <= common_share < 1.0:
        raise InputError(f"the common share of σ̂k² must lie in [0, 1); got {common_share}")
    if common_share == 0.0:
        return two_sided_arl(threshold, reference, 0.0)
    rho = np.sqrt(1.0 - common_share)
    nodes, weights = _gauss_hermite(COMMON_NODES)
    # 1/ARL(β) is even in β: half the nodes suffice.
    half = nodes >= 0
    offsets = np.sqrt(common_share) * nodes[half]
    share = np.where(nodes[half] > 0, 2.0, 1.0) * weights[half]
    rates = [1.0 / two_sided_arl(threshold / rho, reference / rho, beta / rho) for beta in offsets]
    rate = float(np.dot(share, rates))
    return 1.0 / rate if rate > 0 else np.inf


@cache
def _gauss_hermite(n: int) -> tuple[np.ndarray, np.ndarray]:
    nodes, weights = np.polynomial.hermite_e.hermegauss(n)
    return nodes, weights / weights.sum()


def common_share(sigma_k: float, sigma_k_record: float) -> float:
    """The fraction of a verdict's σ̂_k² common to every record of its structure: the fault-mode
    model's own estimation error, (σ̂_k² − σ̂_k,record²)/σ̂_k² (``models.inspection.ModeResult``)."""
    # math.isfinite: the service asks this of every healthy verdict it keeps, at every verdict.
    if not (math.isfinite(sigma_k) and math.isfinite(sigma_k_record)) or sigma_k <= 0 or sigma_k_record < 0:
        raise InputError(f"σ̂k must be positive and finite; got {sigma_k} and {sigma_k_record}")
    return float(max(0.0, 1.0 - (sigma_k_record / sigma_k) ** 2))


@cache
def design_cusum(
    arl_in_control: float, shift: float = DESIGN_SHIFT, common_share: float = 0.0
) -> CusumDesign:
    """The two-sided CUSUM whose in-control ARL is ``arl_in_control`` records.

    Parameters
    ----------
    arl_in_control : target mean number of records between false alarms on a healthy structure
        (e.g. 4 records a day × 365 days = 1460 for one false alarm a year).
    shift : δ, the step (σ units of k̂) the chart is tuned to; the reference is r = δ/2.
    common_share : c, the fraction of σ̂_k² common to all of a structure's records (``common_share``);
        the target is then the ARL averaged over structures (``in_control_arl``).

    Returns
    -------
    CusumDesign with h solving ``in_control_arl(h, r, c)`` = ``arl_in_control`` (Brent's method;
    the ARL increases with h) and the chart's ARL at a step of δ for a structure with β = 0.
    Designs are cached: the service asks for the same few again and again.

    Examples
    --------
    >>> design = design_cusum(1460.0, shift=1.0)
    >>> round(design.threshold, 3), round(design.arl_at_shift, 1)
    (6.134, 12.6)
    """
    if not np.isfinite(arl_in_control) or arl_in_control <= 1.0:
        raise InputError(f"the in-control average run length must exceed one record; got {arl_in_control}")
    if not np.isfinite(shift) or shift <= 0:
        raise InputError(f"the design shift must be positive (σ units); got {shift}")
    reference = shift / 2.0

    def excess(h: float) -> float:
        return np.log(in_control_arl(h, reference, common_share) / arl_in_control)

    if arl_in_control > NEVER / 10:
        raise InputError(
            f"an in-control run length of {arl_in_control:g} records is beyond any service's life"
        )
    upper = 1.0
    while excess(upper) < 0.0:
        upper *= 2.0
        if upper > MAX_THRESHOLD:
            raise InputError(
                f"no decision interval below {MAX_THRESHOLD:g} σ reaches an ARL of {arl_in_control:g} "
                f"records for a shift of {shift:g} σ with a common share of {common_share:g}"
            )
    if excess(1e-6) > 0.0:
        raise InputError(
            f"no CUSUM threshold fits: with a reference of {reference:g} σ a single record beyond it is "
            f"already rarer than one in {arl_in_control:.0f}; give a smaller shift or allow fewer "
            "false alarms"
        )
    threshold = scipy.optimize.brentq(excess, 1e-6, upper, xtol=1e-10)
    rho = np.sqrt(1.0 - common_share)
    return CusumDesign(
        reference=reference,
        threshold=float(threshold),
        arl_in_control=float(arl_in_control),
        arl_at_shift=two_sided_arl(threshold / rho, reference / rho, shift / rho),
        common_share=float(common_share),
    )


def cusum(z: ArrayLike, design: CusumDesign) -> CusumPath:
    """Run the two-sided CUSUM of ``design`` over the standardised estimates ``z`` (σ units).

    Returns both statistics after each observation, the first index at which either exceeds
    the threshold and, for that side, the start of its last run away from zero. The statistics
    go on past the alarm as the recursion defines them; a caller that acts on the alarm restarts
    the chart from the next record (the ARL design assumes that restart).

    Examples
    --------
    >>> path = cusum([0.2, -0.1, 2.0, 2.5, 3.0], design_cusum(100.0, shift=1.0))
    >>> path.alarm_at, path.drift_start
    (4, 2)
    """
    values = _standardised(z)
    r, h = design.reference, design.threshold
    upper = np.empty(values.size)
    lower = np.empty(values.size)
    s_up = s_low = 0.0
    for i, zi in enumerate(values):
        s_up = max(0.0, s_up + zi - r)
        s_low = max(0.0, s_low - zi - r)
        upper[i], lower[i] = s_up, s_low
    beyond = np.flatnonzero((upper > h) | (lower > h))
    if beyond.size == 0:
        return CusumPath(upper=upper, lower=lower, alarm_at=None, drift_start=None)
    alarm_at = int(beyond[0])
    side = upper if upper[alarm_at] > h else lower
    zeros = np.flatnonzero(side[:alarm_at] == 0.0)
    drift_start = int(zeros[-1]) + 1 if zeros.size else 0
    return CusumPath(upper=upper, lower=lower, alarm_at=alarm_at, drift_start=drift_start)


def cusum_chart(z: ArrayLike, design: CusumDesign) -> CusumChart:
    """Run the two-sided CUSUM of ``design`` over ``z`` (σ units), restarting both statistics
    from zero after each alarm, as the ARL design assumes: one pass, where calling
    :func:`cusum` again from each restart costs a pass per alarm.

    Examples
    --------
    >>> chart = cusum_chart([0.2, 3.0, 3.0, 3.0, 0.0, 3.0, 3.0, 3.0], design_cusum(100.0, shift=1.0))
    >>> chart.alarms, chart.drift_starts
    ((2, 5, 7), (1, 3, 6))
    """
    values = _standardised(z)
    r, h = design.reference, design.threshold
    statistic = np.empty(values.size)
    alarms: list[int] = []
    drift_starts: list[int] = []
    s_up = s_low = 0.0
    # The record after the last zero of each side since the last restart: where its run began.
    up_from = low_from = 0
    for i, zi in enumerate(values):
        s_up = max(0.0, s_up + zi - r)
        s_low = max(0.0, s_low - zi - r)
        statistic[i] = max(s_up, s_low)
        if s_up > h or s_low > h:
            alarms.append(i)
            drift_starts.append(up_from if s_up > h else low_from)
            s_up = s_low = 0.0
            up_from = low_from = i + 1
            continue
        if s_up == 0.0:
            up_from = i + 1
        if s_low == 0.0:
            low_from = i + 1
    return CusumChart(statistic, tuple(alarms), tuple(drift_starts))


def _standardised(z: ArrayLike) -> np.ndarray:
    values = np.asarray(z, dtype=float)
    if values.ndim != 1:
        raise InputError("z must be a one-dimensional sequence of standardised estimates")
    if not np.all(np.isfinite(values)):
        raise InputError(
            "z must be finite: a verdict without a standardised estimate has no place in a CUSUM"
        )
    return values


def persistence(flags: Sequence[bool], k: int, m: int) -> bool:
    """True when at least ``k`` of the last ``m`` flags (faulty or unknown verdicts) are set.

    Fewer than m verdicts so far count as they are: k of them must still be set.

    Examples
    --------
    >>> persistence([True, False, True, False, True], k=3, m=5)
    True
    >>> persistence([True, True, False, False, False, False], k=2, m=4)
    False
    """
    if k < 1 or m < k:
        raise InputError(f"persistence needs 1 ≤ k ≤ m; got k = {k}, m = {m}")
    window = list(flags)[-m:]
    return sum(bool(f) for f in window) >= k


def persistence_path(flags: Sequence[bool], k: int, m: int) -> list[bool]:
    """:func:`persistence` after each flag in turn, in one pass: element i is
    ``persistence(flags[: i + 1], k, m)``.

    Examples
    --------
    >>> persistence_path([True, False, True, True, False, False, False], k=2, m=3)
    [False, False, True, True, True, False, False]
    """
    if k < 1 or m < k:
        raise InputError(f"persistence needs 1 ≤ k ≤ m; got k = {k}, m = {m}")
    window = [bool(f) for f in flags]
    held, path = 0, []
    for i, flag in enumerate(window):
        held += flag
        if i >= m:
            held -= window[i - m]
        path.append(held >= k)
    return path


def severity(lower: float, upper: float, threshold: float) -> bool:
    """True when the interval [lower, upper] for k lies wholly beyond ``threshold``.

    A negative threshold (a loss, e.g. −0.05 for 5 % of stiffness lost) needs upper < threshold;
    a positive one needs lower > threshold. Units are those of k (a relative change).

    Examples
    --------
    >>> severity(-0.09, -0.06, -0.05), severity(-0.09, -0.04, -0.05), severity(0.06, 0.08, 0.05)
    (True, False, True)
    """
    if not np.isfinite(threshold) or threshold == 0.0:
        raise InputError(f"a severity threshold must be a non-zero magnitude of k; got {threshold}")
    if lower > upper:
        raise InputError(f"the interval's lower bound {lower} is above its upper bound {upper}")
    return bool(upper < threshold) if threshold < 0 else bool(lower > threshold)


def persistence_alarm_rate(alpha: float, k: int, m: int) -> float:
    """Mean alarms per record of the persistence rule on independent verdicts flagged with probability α.

    Counts onsets — records at which the rule holds and did not hold at the record before — by the
    stationary distribution of the window of the last m flags (a Markov chain on 2^m states).
    """
    if k < 1 or m < k:
        raise InputError(f"persistence needs 1 ≤ k ≤ m; got k = {k}, m = {m}")
    windows = np.arange(2**m)
    counts = np.array([bin(w).count("1") for w in windows])
    probabilities = alpha**counts * (1.0 - alpha) ** (m - counts)  # iid flags: the stationary law
    holds = counts >= k
    rate = 0.0
    for w in np.flatnonzero(~holds):
        for new in (0, 1):
            successor = ((w << 1) | new) & (2**m - 1)
            if holds[successor]:
                rate += probabilities[w] * (alpha if new else 1.0 - alpha)
    return float(rate)


def default_rules(
    records_per_day: float = RECORDS_PER_DAY, modes: int = 1, common_share: float = 0.0
) -> AlarmRules:
    """The rules the service applies unless an admin sets others.

    The CUSUM (reference δ/2 with δ = ``DESIGN_SHIFT``) is designed for one false alarm per
    structure-year at the structure's record rate, shared among its ``modes`` charts (each gets
    ARL = modes × 365 × records_per_day), averaged over the fault-mode models' own error, of which
    ``common_share`` is the fraction of σ̂k² (``common_share()`` of the structure's verdicts; about
    0.06 for the demo's models). Persistence is 3 of the last 5 verdicts, about one onset a year at
    α = 0.05 and four records a day (``persistence_alarm_rate``).
    """
    if not np.isfinite(records_per_day) or records_per_day <= 0:
        raise InputError(f"the record rate must be positive (records a day); got {records_per_day}")
    if modes < 1:
        raise InputError(f"a structure needs at least one fault mode; got {modes}")
    return AlarmRules(
        cusum=design_cusum(modes * 365.0 * records_per_day, DESIGN_SHIFT, round(common_share, 2)),
        persistence_k=PERSISTENCE_K,
        persistence_m=PERSISTENCE_M,
        records_per_day=float(records_per_day),
        modes=int(modes),
    )
