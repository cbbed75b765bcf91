"""The detection figures docs/explanation/decisions.md quotes, computed.

    .venv/bin/python bench/false_alarms.py [--records 3000] [--estimated 1000] [--white 20000]

With the study's settings (simulator.study.StudySettings: 25 kN excitation, 800 N unmeasured force
disturbance, 2000-sample records, α = 0.05, h = 40) it prints:

1. The false-alarm rate with the exact fault-mode models (SPEC §2's coefficients, k2 and k1 over
   [−32, 32] %, no estimation error) on ``--records`` healthy records, with the count a
   Binomial(n, α) stays below with 95 % probability.
2. Ljung–Box's upper tail at N = 2000, h = 40: the share of those healthy records whose
   best-fitting mode's Q exceeds χ²_{1−level}(39), for the nominal levels 5 %, 1.7 % (α/3, the
   adequacy test's first share) and 0.1 % (its share today), with a binomial 95 % interval;
   and the same for Q of ``--white`` series of Gaussian white noise of 2000 samples, against
   χ²(40) and χ²(39). This is why the adequacy test takes a small share of α.
3. False alarms and interval coverage with estimated models, trained anew every 10 records, on
   ``--estimated`` healthy and faulty records (simulator.paper.monte_carlo_checks, which
   tests/test_paper.py asserts on).

Progress goes to stderr; the figures to stdout. Seeds are fixed: a rerun prints the same figures.
"""

from __future__ import annotations

import argparse
import sys
import time

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import numpy as np
from scipy import stats

from models.diagnostics import ljung_box
from models.inspection import inspect
from simulator.paper import monte_carlo_checks
from simulator.simulate import simulate
from simulator.study import StudySettings
from simulator.theory import exact_fault_mode

SETTINGS = StudySettings()
NOMINAL_LEVELS = (0.05, 0.05 / 3, 0.001)


class Progress:
    """A line on stderr every ``every`` steps, with the rate so far."""

    def __init__(self, label: str, total: int, every: int) -> None:
        self.label, self.total, self.every = label, total, every
        self.done = 0
        self.started = time.perf_counter()

    def step(self, *_: object) -> None:
        self.done += 1
        if self.done % self.every == 0 or self.done == self.total:
            elapsed = time.perf_counter() - self.started
            print(f"  {self.label}: {self.done}/{self.total} ({elapsed:.0f} s)", file=sys.stderr, flush=True)


def interval(count: int, n: int) -> str:
    """The rate with its Clopper–Pearson 95 % interval."""
    result = stats.binomtest(count, n).proportion_ci(0.95)
    return f"{100 * count / n:.2f} % ({count}/{n}; 95 % CI {100 * result.low:.2f}–{100 * result.high:.2f} %)"


def exact_models(records: int) -> None:
    k_min, k_max = min(SETTINGS.experiment_k), max(SETTINGS.experiment_k)
    models = [exact_fault_mode(SETTINGS.params, mode, k_min, k_max) for mode in ("k2", "k1")]
    seeds = np.random.SeedSequence([SETTINGS.seed, 20_001]).spawn(records)
    progress = Progress("healthy records, exact models", records, 500)
    alarms = 0
    best_q = np.empty(records)
    for index, seed in enumerate(seeds):
        record = simulate(SETTINGS.scenario(), SETTINGS.inspection_samples, seed)
        verdict = inspect(record.x, record.y, models, alpha=SETTINGS.alpha, lags=SETTINGS.lags)
        alarms += verdict.fault_detected
        best_q[index] = min(verdict.modes, key=lambda m: m.residual_variance).q
        progress.step()
    bound = int(stats.binom.ppf(0.95, records, SETTINGS.alpha))
    print("1. False alarms with the exact fault-mode models (k2, k1), healthy records")
    print(
        f"   {interval(alarms, records)}; a Binomial({records}, {SETTINGS.alpha}) stays ≤ {bound} w.p. 95 %"
    )
    print(f"2. Ljung–Box at N = {SETTINGS.inspection_samples}, h = {SETTINGS.lags}: rejection rates")
    df = SETTINGS.lags - 1
    for level in NOMINAL_LEVELS:
        rejected = int(np.sum(best_q > stats.chi2.isf(level, df)))
        label = f"best-fitting mode's residual vs χ²({df}), nominal {100 * level:.2f} %"
        print(f"   {label}: {interval(rejected, records)}")


def white_noise(series: int) -> None:
    rng = np.random.default_rng(np.random.SeedSequence([SETTINGS.seed, 20_002]))
    progress = Progress("white-noise series", series, 5000)
    q = np.empty(series)
    for index in range(series):
        q[index] = ljung_box(rng.standard_normal(SETTINGS.inspection_samples), SETTINGS.lags).q
        progress.step()
    for df in (SETTINGS.lags, SETTINGS.lags - 1):
        for level in NOMINAL_LEVELS:
            rejected = int(np.sum(q > stats.chi2.isf(level, df)))
            label = f"Gaussian white noise vs χ²({df}), nominal {100 * level:.2f} %"
            print(f"   {label}: {interval(rejected, series)}")


def estimated_models(records: int) -> None:
    progress = Progress("healthy + faulty records, estimated models", records, 100)
    result = monte_carlo_checks(SETTINGS, records, progress.step)
    print(f"3. Estimated models, trained anew every {result['records_per_model']} records")
    print(
        f"   false alarms on healthy records: {interval(result['false_alarms'], records)}; "
        f"a Binomial({records}, {SETTINGS.alpha}) stays ≤ {result['false_alarm_binomial_95_bound']} w.p. 95 %"
    )
    print(
        f"   95 % interval coverage, faulty records over k ∈ [−32, 32] in both modes: "
        f"{result['coverage_with_model_term']:.3f} with the model term, "
        f"{result['coverage_paper_sigma']:.3f} without; "
        f"|k| > 24: {result['coverage_near_range_ends_with_model_term']:.3f} with, "
        f"{result['coverage_near_range_ends_paper_sigma']:.3f} without"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--records", type=int, default=3000, help="healthy records with the exact models")
    parser.add_argument("--white", type=int, default=20_000, help="white-noise series for Ljung–Box")
    parser.add_argument("--estimated", type=int, default=1000, help="records with estimated models (0: skip)")
    args = parser.parse_args()
    exact_models(args.records)
    white_noise(args.white)
    if args.estimated:
        estimated_models(args.estimated)


if __name__ == "__main__":
    main()
