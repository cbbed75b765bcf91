"""Free-run simulation of a NARX structure, compiled.

A free run computes ŷ[t] = Σ_j θ_j φ_j(ŷ, x)[t] for t = L … N−1 from the first L measured outputs,
each ŷ[t] feeding the regressors of the samples after it. The recursion cannot be vectorised in
time, and simulation-error criteria (output-error fits, structure selection on the free run) need
thousands of runs of the same structure over the same input, so it is split:

- everything that does not read the output — powers of x, sinusoids of t, the constant — is
  computed once per record by :class:`FreeRun` as the columns of the exogenous terms and the
  known multipliers of the autoregressive ones;
- the recursion over the output factors is a loop compiled by numba (about a hundred times
  faster than the same loop in Python), run for each θ by :meth:`FreeRun.run`; it transforms
  each simulated sample once (its powers, |ŷ|^p, the difference to the sample before) and every
  lag reads that back, where each factor would transform its sample again (Silverbox's 51-term
  model: a run 36 % faster, one with sensitivities 24 %, the same to the last digit).

A run that leaves ±``DIVERGED`` (or becomes NaN) stops there; the samples from that one on are NaN.
A run may be given output limits: each ŷ[t] is then clipped to them before it feeds the samples
after it, as a tank's level stays at its overflow or a mass against its end stop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba
import numpy as np

from models.terms import Factor, Term, bouc_wen_step, max_lag

# Free-run outputs beyond this magnitude mean the simulated model has diverged.
DIVERGED = 1e100
# How an output factor transforms its value before the power: the codes the kernel knows.
FUNCTION_CODES = {"": 0, "abs": 1, "sign": 2, "spow": 3, "apow": 4, "boucwen": 5}


@dataclass(frozen=True)
class FreeRun:
    """The free run of fixed terms driven by a fixed input, ready to run for any θ.

    Attributes
    ----------
    exogenous : (N, E) columns of the terms without output factors; ``exogenous_terms`` their
        indices among the terms.
    known : (N, K) the non-output part of the autoregressive terms that have one (an input
        factor, a sinusoid); ``known_column`` (R,) each autoregressive term's column there, −1
        for a term of the output alone, whose part is one (most terms: kept out, their columns
        of ones would be most of what a run reads); ``recursive_terms`` their indices.
    factor_start : (R + 1,) where each autoregressive term's output factors begin in the
        flattened ``difference``/``lag``/``function``/``parameter``/``shape`` arrays (one entry a
        factor; a difference factor reads ŷ[t−lag] − ŷ[t−lag−1]; ``parameter`` is a power law's
        exponent, a Bouc–Wen variable's level, ``shape`` that variable's shape; the kernel runs
        that variable of ŷ from the first sample on).
    factor_feature : (F,) each factor's feature: what it reads of one sample, transformed and
        raised to its power, the same for every lag (−1 for a Bouc–Wen factor); the features'
        ``feature_difference``/``feature_function``/``feature_power``/``feature_parameter``. The
        kernel computes a feature once for each simulated sample, where each of its factors would
        compute it again at each lag: y[t−1]³ and y[t−3]³ read the same feature of two samples.
    """

    n: int
    lag: int
    exogenous_terms: np.ndarray
    exogenous: np.ndarray
    recursive_terms: np.ndarray
    known: np.ndarray
    known_column: np.ndarray
    factor_start: np.ndarray
    difference: np.ndarray
    factor_lag: np.ndarray
    function: np.ndarray
    parameter: np.ndarray
    shape: np.ndarray
    factor_feature: np.ndarray
    feature_difference: np.ndarray
    feature_function: np.ndarray
    feature_power: np.ndarray
    feature_parameter: np.ndarray

    @classmethod
    def build(cls, terms: Sequence[Term], x: np.ndarray, t0: int = 0) -> FreeRun:
        """Precompute the input side of ``terms`` over ``x``; sinusoids count time from ``t0``."""
        n = x.size
        times = np.arange(t0, t0 + n, dtype=np.float64)

        def lagged_x(k: int) -> np.ndarray:
            lagged = np.zeros(n)
            lagged[k:] = x[: n - k]
            return lagged

        exogenous_terms: list[int] = []
        exogenous: list[np.ndarray] = []
        recursive_terms: list[int] = []
        known: list[np.ndarray] = []
        known_column: list[int] = []
        factors: list[Factor] = []
        starts = [0]
        for index, term in enumerate(terms):
            output_factors = [f for f in term.factors if f.autoregressive]
            others = [f for f in term.factors if not f.autoregressive]
            # The product of the input's and time's factors (reads x or t only), the first factor's
            # values themselves (1·v is v); the constant's column is ones.
            column = np.ones(n) if not term.factors else None
            for factor in others:
                values = factor.values(lagged_x, lagged_x, times)
                column = values if column is None else column * values
            if output_factors:
                recursive_terms.append(index)
                known_column.append(len(known) if others else -1)
                if others:
                    known.append(column)
                factors.extend(output_factors)
                starts.append(len(factors))
            else:
                exogenous_terms.append(index)
                exogenous.append(column)
        features: dict[tuple[bool, int, int, float], int] = {}
        factor_feature = [
            -1
            if factor.function == "boucwen"
            else features.setdefault(
                (factor.signal == "dy", FUNCTION_CODES[factor.function], factor.power, factor.parameter),
                len(features),
            )
            for factor in factors
        ]
        return cls(
            n=n,
            lag=max_lag(terms),
            exogenous_terms=np.asarray(exogenous_terms, dtype=np.int64),
            exogenous=np.column_stack(exogenous) if exogenous else np.zeros((n, 0)),
            recursive_terms=np.asarray(recursive_terms, dtype=np.int64),
            known=np.column_stack(known) if known else np.zeros((n, 0)),
            known_column=np.asarray(known_column, dtype=np.int64),
            factor_start=np.asarray(starts, dtype=np.int64),
            difference=np.asarray([f.signal == "dy" for f in factors], dtype=np.bool_),
            factor_lag=np.asarray([f.lag for f in factors], dtype=np.int64),
            function=np.asarray([FUNCTION_CODES[f.function] for f in factors], dtype=np.int64),
            parameter=np.asarray([f.parameter for f in factors], dtype=np.float64),
            shape=np.asarray([f.shape for f in factors], dtype=np.float64),
            factor_feature=np.asarray(factor_feature, dtype=np.int64),
            feature_difference=np.asarray([key[0] for key in features], dtype=np.bool_),
            feature_function=np.asarray([key[1] for key in features], dtype=np.int64),
            feature_power=np.asarray([key[2] for key in features], dtype=np.int64),
            feature_parameter=np.asarray([key[3] for key in features], dtype=np.float64),
        )

    def rows(self, first: int, last: int) -> FreeRun:
        """The run over samples ``first`` … ``last`` − 1 alone, started there from its first L:
        the same as built on that part of the input, whose rows from the L-th on see the same
        lagged input and times."""
        return replace(
            self, n=last - first, exogenous=self.exogenous[first:last], known=self.known[first:last]
        )

    def measured_to(self, sample: int) -> FreeRun:
        """The run with its outputs measured up to ``sample`` (at least its first L) and simulated
        from there: a Bouc–Wen variable of the output is run over the measured ones, as the
        output's lags are read from them."""
        return replace(self, lag=max(self.lag, sample))

    @classmethod
    def stacked(cls, runs: Sequence[FreeRun]) -> FreeRun:
        """Runs of the same terms one after the other as the rows of one (the parts of
        :meth:`run_windows`): each part's rows are its run's."""
        first = runs[0]
        return replace(
            first,
            n=sum(run.n for run in runs),
            exogenous=np.concatenate([run.exogenous for run in runs]),
            known=np.concatenate([run.known for run in runs]),
        )

    def run_windows(
        self,
        theta: np.ndarray,
        windows: np.ndarray,
        initial: Sequence[np.ndarray],
        limits: tuple[float, float] | None = None,
    ) -> np.ndarray:
        """The runs over rows a … b − 1 of this one for each window (a, b) of ``windows``, each
        started from its row of ``initial`` (its first L outputs): row w what :meth:`rows` of
        window w runs from them, to the last digit (NaN beyond the window's length).

        The windows are run side by side, a sample of each in turn: a run is a chain of
        dependent products, one sample waiting for the last, and independent runs interleaved
        keep the processor busy while each waits (a ring-down of a short record's model costs
        a third of its own run's time so), where each run alone would also cost a call's
        preparation."""
        windows = np.asarray(windows, dtype=np.int64).reshape(-1, 2)
        lengths = windows[:, 1] - windows[:, 0]
        out = np.full((lengths.size, int(lengths.max(initial=0))), np.nan)
        exogenous_theta = theta[self.exogenous_terms]
        for w, ((a, b), state) in enumerate(zip(windows, initial, strict=True)):
            lag = min(self.lag, int(b - a))
            out[w, :lag] = state[:lag]
        # Each window's drive by its own product: BLAS's sums over a block of rows depend on
        # where the block starts, and a run's rows must add as :meth:`rows`' do. Windows that
        # tile the run (runs stacked) are its blocks: one stacked product, a product a block.
        count, width = out.shape
        if count * width == self.n and np.array_equal(windows[:, 0], np.arange(count) * width):
            blocks = self.exogenous.reshape(count, width, self.exogenous.shape[1])
            drive = np.matmul(blocks, exogenous_theta)
        else:
            drive = np.zeros(out.shape)
            for w, (a, b) in enumerate(windows):
                drive[w, : b - a] = self.exogenous[a:b] @ exogenous_theta
        low, high = limits or (-np.inf, np.inf)
        _side_by_side(
            out,
            lengths,
            windows[:, 0].copy(),
            self.lag,
            drive,
            theta[self.recursive_terms],
            *self._factors,
            low,
            high,
            *self._features,
        )
        return out

    @property
    def _factors(self) -> tuple[np.ndarray, ...]:
        """The output factors' arrays, in the order the compiled kernels take them."""
        return (
            self.known,
            self.known_column,
            self.factor_start,
            self.difference,
            self.factor_lag,
            self.function,
            self.parameter,
            self.shape,
        )

    @property
    def _features(self) -> tuple[np.ndarray, ...]:
        """The factors' shared features' arrays, in the order the compiled kernels take them."""
        return (
            self.factor_feature,
            self.feature_difference,
            self.feature_function,
            self.feature_power,
            self.feature_parameter,
        )

    def run(
        self, theta: np.ndarray, y_initial: np.ndarray, limits: tuple[float, float] | None = None
    ) -> np.ndarray:
        """The simulated output for every sample, the first L being ``y_initial``; NaN from the
        sample where the run diverged on. With ``limits`` = (low, high) every simulated sample
        is clipped to them."""
        out, _ = self._run(theta, y_initial, limits, sensitivities=False)
        return out

    def run_with_sensitivities(
        self,
        theta: np.ndarray,
        y_initial: np.ndarray,
        limits: tuple[float, float] | None = None,
        into: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The simulated output and its sensitivities S[t, j] = ∂ŷ[t]/∂θ_j (zero over the first L
        samples, which are measured, and where a limit holds ŷ[t]), by the recursion

            S[t] = φ[t](ŷ) + Σ_k (∂F/∂ŷ[t−k]) · S[t−k],

        with F the model's right-hand side: the Jacobian of the free-run error in one pass, where
        finite differences would take a run per parameter. A Bouc–Wen factor's own memory of ŷ is
        left out of ∂F/∂ŷ (its value enters φ exactly): the Jacobian is then approximate, which
        slows a search but does not mislead it, since a step is kept only if it lowers the error.
        Rows from a divergence on are NaN. ``into``, an (N, p) array, receives S from row L on
        (its first L rows are left as they are): a search reuses one, where a fresh array costs
        its pages' first writes (4 ms on Silverbox's 65 000 × 51, a tenth of this run)."""
        return self._run(theta, y_initial, limits, sensitivities=True, into=into)

    def _run(
        self,
        theta: np.ndarray,
        y_initial: np.ndarray,
        limits: tuple[float, float] | None,
        sensitivities: bool,
        into: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        out = np.full(self.n, np.nan)
        L = min(self.lag, self.n)
        out[:L] = y_initial[:L]
        # Every row of ``into`` from L on is written: each column is a term's, autoregressive or not.
        S = np.zeros((self.n if sensitivities else 0, theta.size)) if into is None else into
        low, high = limits or (-np.inf, np.inf)
        if self.n > L:
            _recursion(
                out,
                L,
                self.exogenous @ theta[self.exogenous_terms],
                theta[self.recursive_terms],
                self.recursive_terms,
                *self._factors,
                low,
                high,
                self.exogenous,
                self.exogenous_terms,
                S,
                *self._features,
            )
        return out, S


@numba.njit(cache=True, nogil=True)
def _recursion(
    out: np.ndarray,
    start: int,
    drive: np.ndarray,
    coefficients: np.ndarray,
    columns: np.ndarray,
    known: np.ndarray,
    known_column: np.ndarray,
    factor_start: np.ndarray,
    difference: np.ndarray,
    factor_lag: np.ndarray,
    function: np.ndarray,
    parameter: np.ndarray,
    shape: np.ndarray,
    low: float,
    high: float,
    exogenous: np.ndarray,
    exogenous_columns: np.ndarray,
    S: np.ndarray,
    factor_feature: np.ndarray,
    feature_difference: np.ndarray,
    feature_function: np.ndarray,
    feature_power: np.ndarray,
    feature_parameter: np.ndarray,
) -> None:
    """The free run (into ``out``) and, when S has rows, its sensitivities (into S): see
    :meth:`FreeRun.run_with_sensitivities`. ``columns`` are the autoregressive terms' places in θ."""
    n = out.size
    terms = coefficients.size
    with_sensitivities = S.shape[0] > 0
    reach = 1
    for f in range(factor_lag.size):
        reach = max(reach, factor_lag[f] + 1 + difference[f])
    slope = np.zeros(reach)  # ∂F/∂ŷ[t−k] at this step
    slopes = np.zeros(factor_lag.size)  # each factor's slope with respect to its base
    values = np.zeros(factor_lag.size)
    # Each feature's value and its slope d(value)/d(raw) at the last samples, sample s in row
    # s & mask: a ring of a power of two rows at least ``reach``, where a remainder would cost
    # more than the features themselves.
    rows = 1
    while rows < reach:
        rows *= 2
    mask = rows - 1
    cached = np.zeros((rows, feature_function.size))
    cached_slope = np.zeros((rows, feature_function.size))
    # Bouc–Wen variables of the output: one row for each boucwen factor (none for most models).
    bouc_wen = np.nonzero(function == 5)[0]
    row = np.full(function.size, -1)
    row[bouc_wen] = np.arange(bouc_wen.size)
    hysteretic = np.zeros((bouc_wen.size, n))
    for i, f in enumerate(bouc_wen):
        for t in range(1, start):
            step = out[t] - out[t - 1]
            hysteretic[i, t] = bouc_wen_step(hysteretic[i, t - 1], step, parameter[f], shape[f])
    for s in range(max(0, start - reach), start):
        _features(
            out, s, s & mask, cached, cached_slope, feature_difference, feature_function, feature_power,
            feature_parameter, with_sensitivities,
        )  # fmt: skip
    for t in range(start, n):
        total = drive[t]
        if with_sensitivities:
            slope[:] = 0.0
        for j in range(terms):
            first, last = factor_start[j], factor_start[j + 1]
            product = 1.0 if known_column[j] < 0 else known[t, known_column[j]]
            if last == first + 1 and function[first] != 5:
                # One factor, most terms: the others' product is the known part alone. A path of
                # its own, the general one's loops over the factors cost a tenth of a run.
                at, feature = (t - factor_lag[first]) & mask, factor_feature[first]
                others = product
                product *= cached[at, feature]
                total += coefficients[j] * product
                if not with_sensitivities:
                    continue
                S[t, columns[j]] = product
                if cached_slope[at, feature] != 0.0:
                    contribution = coefficients[j] * others * cached_slope[at, feature]
                    slope[factor_lag[first]] += contribution
                    if difference[first]:
                        slope[factor_lag[first] + 1] -= contribution
                continue
            for f in range(first, last):
                k = factor_lag[f]
                if function[f] == 5:
                    values[f] = hysteretic[row[f], t - k]
                    slopes[f] = 0.0
                else:
                    values[f] = cached[(t - k) & mask, factor_feature[f]]
                    slopes[f] = cached_slope[(t - k) & mask, factor_feature[f]]
                product *= values[f]
            total += coefficients[j] * product
            if not with_sensitivities:
                continue
            S[t, columns[j]] = product
            for f in range(first, last):
                if slopes[f] == 0.0:
                    continue
                others = 1.0 if known_column[j] < 0 else known[t, known_column[j]]
                for g in range(first, last):
                    if g != f:
                        others *= values[g]
                contribution = coefficients[j] * others * slopes[f]
                slope[factor_lag[f]] += contribution
                if difference[f]:
                    slope[factor_lag[f] + 1] -= contribution
        if not abs(total) < DIVERGED:
            if with_sensitivities:
                S[t:, :] = np.nan
            return
        out[t] = min(max(total, low), high)
        _features(
            out, t, t & mask, cached, cached_slope, feature_difference, feature_function, feature_power,
            feature_parameter, with_sensitivities,
        )  # fmt: skip
        for i, f in enumerate(bouc_wen):
            step = out[t] - out[t - 1]
            hysteretic[i, t] = bouc_wen_step(hysteretic[i, t - 1], step, parameter[f], shape[f])
        if with_sensitivities:
            if out[t] != total:  # held at a limit: no parameter moves it
                S[t, :] = 0.0
                continue
            for e in range(exogenous_columns.size):
                S[t, exogenous_columns[e]] = exogenous[t, e]
            for k in range(1, reach):
                if slope[k] != 0.0 and t - k >= start:
                    for column in range(S.shape[1]):  # a loop: a slice expression would allocate
                        S[t, column] += slope[k] * S[t - k, column]


@numba.njit(cache=True, nogil=True)
def _side_by_side(
    out: np.ndarray,
    lengths: np.ndarray,
    first_rows: np.ndarray,
    start: int,
    drive: np.ndarray,
    coefficients: np.ndarray,
    known: np.ndarray,
    known_column: np.ndarray,
    factor_start: np.ndarray,
    difference: np.ndarray,
    factor_lag: np.ndarray,
    function: np.ndarray,
    parameter: np.ndarray,
    shape: np.ndarray,
    low: float,
    high: float,
    factor_feature: np.ndarray,
    feature_difference: np.ndarray,
    feature_function: np.ndarray,
    feature_power: np.ndarray,
    feature_parameter: np.ndarray,
) -> None:
    """:func:`_recursion`'s free runs without sensitivities, run r into row r of ``out`` (its
    first ``lengths`` r samples) with its drive in row r of ``drive`` and the rows of ``known``
    from ``first_rows`` r on: a sample of every run in turn, each run's sums in the order its
    own run adds them."""
    runs = out.shape[0]
    terms = coefficients.size
    reach = 1
    for f in range(factor_lag.size):
        reach = max(reach, factor_lag[f] + 1 + difference[f])
    rows = 1
    while rows < reach:
        rows *= 2
    mask = rows - 1
    cached = np.zeros((runs, rows, feature_function.size))
    unused = np.zeros((rows, feature_function.size))  # the slopes, not asked for
    bouc_wen = np.nonzero(function == 5)[0]
    row = np.full(function.size, -1)
    row[bouc_wen] = np.arange(bouc_wen.size)
    hysteretic = np.zeros((runs, bouc_wen.size, out.shape[1]))
    live = lengths > start
    total = np.zeros(runs)
    for r in range(runs):
        if not live[r]:
            continue
        for i, f in enumerate(bouc_wen):
            for t in range(1, start):
                step = out[r, t] - out[r, t - 1]
                hysteretic[r, i, t] = bouc_wen_step(hysteretic[r, i, t - 1], step, parameter[f], shape[f])
        for s in range(max(0, start - reach), start):
            _features(
                out[r], s, s & mask, cached[r], unused, feature_difference, feature_function,
                feature_power, feature_parameter, False,
            )  # fmt: skip
    for t in range(start, out.shape[1]):
        for r in range(runs):
            live[r] = live[r] and t < lengths[r]
            total[r] = drive[r, t]
        for j in range(terms):
            first, last = factor_start[j], factor_start[j + 1]
            column = known_column[j]
            if last == first + 1 and function[first] != 5:
                at, feature = (t - factor_lag[first]) & mask, factor_feature[first]
                for r in range(runs):
                    if live[r]:
                        product = 1.0 if column < 0 else known[first_rows[r] + t, column]
                        product *= cached[r, at, feature]
                        total[r] += coefficients[j] * product
                continue
            for r in range(runs):
                if not live[r]:
                    continue
                product = 1.0 if column < 0 else known[first_rows[r] + t, column]
                for f in range(first, last):
                    k = factor_lag[f]
                    if function[f] == 5:
                        product *= hysteretic[r, row[f], t - k]
                    else:
                        product *= cached[r, (t - k) & mask, factor_feature[f]]
                total[r] += coefficients[j] * product
        for r in range(runs):
            if not live[r]:
                continue
            if not abs(total[r]) < DIVERGED:
                live[r] = False  # the rest of the run stays NaN
                continue
            out[r, t] = min(max(total[r], low), high)
            _features(
                out[r], t, t & mask, cached[r], unused, feature_difference, feature_function,
                feature_power, feature_parameter, False,
            )  # fmt: skip
            for i, f in enumerate(bouc_wen):
                step = out[r, t] - out[r, t - 1]
                hysteretic[r, i, t] = bouc_wen_step(hysteretic[r, i, t - 1], step, parameter[f], shape[f])


@numba.njit(cache=True, nogil=True, inline="always")
def _features(
    out: np.ndarray,
    s: int,
    into: int,
    cached: np.ndarray,
    cached_slope: np.ndarray,
    difference: np.ndarray,
    function: np.ndarray,
    power: np.ndarray,
    parameter: np.ndarray,
    with_slopes: bool,
) -> None:
    """Every feature of sample ``s`` (:class:`FreeRun`) into row ``into`` of ``cached``, and
    with ``with_slopes`` its slope d(value)/d(raw) into ``cached_slope``: raw the output ŷ[s],
    or its difference ŷ[s] − ŷ[s−1] (none for s = 0, which no factor reads)."""
    for q in range(function.size):
        if difference[q] and s < 1:
            continue
        raw = out[s] - out[s - 1] if difference[q] else out[s]
        if function[q] == 0 and power[q] == 1:  # the sample itself, most features: no products
            cached[into, q] = raw
            if with_slopes:
                cached_slope[into, q] = 1.0
            continue
        sign = (raw > 0.0) - (raw < 0.0)
        base, rate = raw, 1.0  # the transformed value and its slope d(base)/d(raw)
        if function[q] == 1:
            base, rate = abs(raw), sign
        elif function[q] == 2:
            base, rate = sign, 0.0
        elif function[q] == 3:
            base = sign * abs(raw) ** parameter[q]
            rate = parameter[q] * abs(raw) ** (parameter[q] - 1.0) if raw != 0.0 else 0.0
        elif function[q] == 4:
            base = abs(raw) ** parameter[q]
            rate = sign * parameter[q] * abs(raw) ** (parameter[q] - 1.0) if raw != 0.0 else 0.0
        value = 1.0
        for _ in range(power[q]):
            value *= base
        cached[into, q] = value
        if not with_slopes:
            continue
        derivative = power[q] * rate
        for _ in range(power[q] - 1):
            derivative *= base
        cached_slope[into, q] = derivative
