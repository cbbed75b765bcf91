"""Alarm rules on simulated streams, through the real inspection chain: false alarms and delays.

    python -m bench.alarms [--structures 40] [--years 2] [--drifts 200] [--seed 2026]

Each simulated structure has fault-mode models of its own (k2 and k1, trained as the demo trains
them: 17 experiments of 2000 samples each, ``simulator.paper.train_fault_modes``), and its records
(2000 samples, the study's 25 kN excitation and 800 N disturbance) are inspected by
``models.inspection.inspect`` at α = 0.05, h = 40, as the service inspects an upload. The rules
are those of ``models.alarms.default_rules`` at four records a day, the CUSUM designed with the
structure's own common share of σ̂k² (from its first verdict):

- *CUSUM*: a two-sided chart per fault mode on z = k̂/σ̂k, restarted after each alarm;
- *persistence*: 3 of the last 5 verdicts faulty or unknown; an alarm opens when the rule holds
  and none is open, and closes when the rule has not held for 5 records (the alarm lifecycle);
- *one record*: every faulty or unknown verdict (today's behaviour: one record turns the status red).

(a) Healthy streams: alarms per structure-year of each rule against its design, with the range
    the design's own count distribution puts 99 % of counts in (for the CUSUM, a Poisson count per
    chart whose rate is that of the structure's model offset β ~ N(0, c), drawn anew each time).
(b) A drift of ``--rate`` % a day in k2 from onset after a healthy week (``narxwatch-sim stream
    --scenario drift``'s course, simulator.client.scheduler.Stream): the median delay from the onset to
    each rule's first alarm, in days.

Seeds are fixed: a rerun prints the same figures. Progress goes to stderr, the table to stdout.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from functools import cache

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import numpy as np
from scipy import stats

from models.alarms import (
    RECORDS_PER_DAY,
    AlarmRules,
    CusumDesign,
    common_share,
    cusum_chart,
    default_rules,
    persistence,
    persistence_alarm_rate,
    two_sided_arl,
)
from models.inspection import Verdict, inspect
from simulator.client.scheduler import Course, ScenarioOptions, Stream
from simulator.paper import train_fault_modes
from simulator.simulate import Scenario, simulate
from simulator.study import StudySettings

SETTINGS = StudySettings()
MODES = ("k2", "k1")
RECORDS_PER_YEAR = 365 * RECORDS_PER_DAY
HEALTHY_PREFIX = 28  # a week of healthy records before a drift's onset
OPTIONS = ScenarioOptions(SETTINGS.excitation_std, SETTINGS.disturbance_std, 0.0, 0.0, (), ())
RULES = ("cusum", "persistence", "record")


@dataclass(frozen=True)
class Verdicts:
    """One structure's verdicts in record order, as the rules read them."""

    z: np.ndarray  # records × modes: k̂/σ̂k of each mode
    flagged: np.ndarray  # records: faulty or unknown
    rules: AlarmRules


def structure_verdicts(seed: np.random.SeedSequence, course: Stream, records: int) -> Verdicts:
    """Train a structure's models, then simulate and inspect ``records`` records of ``course``."""
    training, streaming = seed.spawn(2)
    models = train_fault_modes(SETTINGS, iter(training.spawn(2 * len(SETTINGS.experiment_k))))
    seeds = streaming.spawn(records)
    verdicts: list[Verdict] = []
    for index in range(records):
        record = simulate(scenario(*course.fault_at(index)), SETTINGS.inspection_samples, seeds[index])
        verdicts.append(inspect(record.x, record.y, models.both, alpha=SETTINGS.alpha, lags=SETTINGS.lags))
    # The service knows the common share from its verdicts; the largest of the modes' is the safe one.
    share = max(common_share(m.sigma_k, m.sigma_k_record) for m in verdicts[0].modes)
    return Verdicts(
        z=np.array([[v.mode(name).z for name in MODES] for v in verdicts]),
        flagged=np.array([v.status != "healthy" for v in verdicts]),
        rules=default_rules(RECORDS_PER_DAY, len(MODES), share),
    )


@cache
def scenario(fault: str, k: float) -> Scenario:
    """One scenario object per course step, so that its structure's stability bound is computed once."""
    return OPTIONS.scenario(fault, k)


def persistence_alarms(flagged: np.ndarray, rules: AlarmRules) -> list[int]:
    """Records at which a persistence alarm opens: the rule holds and no alarm is open; an open
    alarm closes once the rule has not held for m records."""
    k, m = rules.persistence_k, rules.persistence_m
    alarms = []
    open_alarm = False
    clear = 0
    for index in range(flagged.size):
        holds = persistence(flagged[max(0, index - m + 1) : index + 1], k, m)
        if holds and not open_alarm:
            alarms.append(index)
            open_alarm = True
        clear = 0 if holds else clear + 1
        if open_alarm and clear >= m:
            open_alarm = False
    return alarms


def alarms_by_rule(verdicts: Verdicts) -> dict[str, list[int]]:
    charts = [list(cusum_chart(verdicts.z[:, j], verdicts.rules.cusum).alarms) for j in range(len(MODES))]
    return {
        "cusum": sorted(index for chart in charts for index in chart),
        "persistence": persistence_alarms(verdicts.flagged, verdicts.rules),
        "record": [int(i) for i in np.flatnonzero(verdicts.flagged)],
    }


@dataclass(frozen=True)
class HealthyResult:
    structure_years: float
    records: int
    counts: dict[str, int]
    flag_rate: float
    designs: list[CusumDesign]  # one per structure (each of its charts has it)

    def rate(self, rule: str) -> float:
        return self.counts[rule] / self.structure_years


def healthy_study(structures: int, years: float, seed: int, progress: bool = True) -> HealthyResult:
    """(a): ``structures`` structures with models of their own, ``years`` of healthy records each."""
    records = round(years * RECORDS_PER_YEAR)
    course = Stream(
        OPTIONS, "none", 0.0, 0.0, SETTINGS.inspection_samples, 0, 0.0, records, None, Course.healthy
    )
    counts = dict.fromkeys(RULES, 0)
    flags = 0
    designs = []
    began = time.perf_counter()
    for index, structure_seed in enumerate(np.random.SeedSequence([seed, 1]).spawn(structures)):
        verdicts = structure_verdicts(structure_seed, course, records)
        for rule, alarms in alarms_by_rule(verdicts).items():
            counts[rule] += len(alarms)
        flags += int(verdicts.flagged.sum())
        designs.append(verdicts.rules.cusum)
        if progress:
            elapsed = time.perf_counter() - began
            print(
                f"  healthy structure {index + 1}/{structures} ({elapsed:.0f} s)", file=sys.stderr, flush=True
            )
    return HealthyResult(
        structures * years, structures * records, counts, flags / (structures * records), designs
    )


def cusum_count_range(designs: list[CusumDesign], records: int, level: float, seed: int) -> tuple[int, int]:
    """The central ``level`` range of the CUSUM's false-alarm count as its design has it.

    Each chart (a mode of a structure) has an offset β ~ N(0, c) of its own and alarms at the
    rate 1/ARL(h | β) (``models.alarms.in_control_arl``), a Poisson count over ``records``; the
    count of the study is their sum, drawn here 20 000 times.
    """
    rng = np.random.default_rng(seed)
    draws = 20_000
    total = np.zeros(draws)
    grid = np.linspace(-6.0, 6.0, 97)  # β in units of √c; log-rate interpolated between
    for design in designs:
        rho = np.sqrt(1.0 - design.common_share)
        offsets = np.sqrt(design.common_share) * grid / rho
        log_rates = -np.log(
            [two_sided_arl(design.threshold / rho, design.reference / rho, b) for b in offsets]
        )
        for _ in MODES:
            rates = np.exp(np.interp(rng.standard_normal(draws), grid, log_rates))
            total += rng.poisson(records * rates)
    low, high = np.quantile(total, [(1 - level) / 2, (1 + level) / 2])
    return int(low), int(high)


@dataclass(frozen=True)
class DriftResult:
    rate: float
    structures: int
    delays: dict[str, np.ndarray]  # days from the onset; inf when no alarm within the horizon

    def median(self, rule: str) -> float:
        return float(np.median(self.delays[rule]))


def drift_study(
    structures: int, rate: float, horizon_days: float, seed: int, progress: bool = True
) -> DriftResult:
    """(b): a week healthy, then k2 growing at ``rate`` % a day for ``horizon_days``."""
    onset_days = HEALTHY_PREFIX / RECORDS_PER_DAY
    records = HEALTHY_PREFIX + round(horizon_days * RECORDS_PER_DAY) + 1
    course = Stream(
        OPTIONS, "k2", 0.0, 0.0, SETTINGS.inspection_samples, 0, 0.0, records, None,
        Course.drift, onset=onset_days, rate=rate, per_day=RECORDS_PER_DAY,
    )  # fmt: skip
    delays = {rule: np.full(structures, np.inf) for rule in RULES}
    began = time.perf_counter()
    for index, structure_seed in enumerate(
        np.random.SeedSequence([seed, 2, round(rate * 1000)]).spawn(structures)
    ):
        verdicts = structure_verdicts(structure_seed, course, records)
        for rule, alarms in alarms_by_rule(verdicts).items():
            after = [i for i in alarms if i > HEALTHY_PREFIX]  # record HEALTHY_PREFIX has k = 0
            if after:
                delays[rule][index] = (after[0] - HEALTHY_PREFIX) / RECORDS_PER_DAY
        if progress and (index + 1) % 10 == 0:
            elapsed = time.perf_counter() - began
            print(
                f"  drift structure {index + 1}/{structures} ({elapsed:.0f} s)", file=sys.stderr, flush=True
            )
    return DriftResult(rate, structures, delays)


def report(healthy: HealthyResult, drifts: list[DriftResult], seed: int) -> str:
    """The two tables docs/explanation/alarms-design.md quotes, in Markdown."""
    structures = len(healthy.designs)
    low, high = cusum_count_range(healthy.designs, round(healthy.records / structures), 0.99, seed)
    at_alpha = persistence_alarm_rate(SETTINGS.alpha, 3, 5) * RECORDS_PER_YEAR
    at_measured = persistence_alarm_rate(healthy.flag_rate, 3, 5) * RECORDS_PER_YEAR
    flagged = round(healthy.flag_rate * healthy.records)
    ci = stats.binomtest(flagged, healthy.records).proportion_ci(0.99)
    shares = [d.common_share for d in healthy.designs]
    thresholds = [d.threshold for d in healthy.designs]
    rate = healthy.rate
    lines = [
        f"(a) healthy streams: {structures} structures × {healthy.structure_years / structures:g} years at "
        f"{RECORDS_PER_DAY:g} records a day ({healthy.records} records inspected); common share c "
        f"{min(shares):.2f}–{max(shares):.2f}, CUSUM r = {healthy.designs[0].reference:g}, "
        f"h {min(thresholds):.2f}–{max(thresholds):.2f}",
        "",
        "| rule | alarms | per structure-year | design | design's 99 % range |",
        "|---|---|---|---|---|",
        f"| CUSUM, both modes | {healthy.counts['cusum']} | {rate('cusum'):.2f} | 1 | {low}–{high} |",
        f"| persistence 3 of 5 | {healthy.counts['persistence']} | {rate('persistence'):.2f} | "
        f"{at_alpha:.2f} at α, {at_measured:.2f} at the verdicts' measured rate | – |",
        f"| CUSUM or persistence | {healthy.counts['cusum'] + healthy.counts['persistence']} | "
        f"{rate('cusum') + rate('persistence'):.2f} | {1 + at_alpha:.2f} | – |",
        f"| one record (today) | {healthy.counts['record']} | {rate('record'):.1f} | "
        f"{SETTINGS.alpha * RECORDS_PER_YEAR:.0f} (α × records) | flagged {100 * healthy.flag_rate:.2f} % "
        f"(99 % CI {100 * ci.low:.2f}–{100 * ci.high:.2f} %) |",
        "",
        "(b) drift in k2 from onset after a healthy week: days from the onset to the first alarm,",
        "median [quartiles]",
        "",
        "| drift | structures | CUSUM | persistence 3 of 5 | one record (today) |",
        "|---|---|---|---|---|",
    ]
    for drift in drifts:
        cells = []
        for rule in RULES:
            q1, q2, q3 = np.quantile(drift.delays[rule], [0.25, 0.5, 0.75])
            missed = int(np.isinf(drift.delays[rule]).sum())
            cells.append(f"{q2:.2f} [{q1:.2f}, {q3:.2f}]" + (f", {missed} later" if missed else ""))
        lines.append(f"| {drift.rate:g} % a day | {drift.structures} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--structures", type=int, default=40, help="healthy structures, each with its own models"
    )
    parser.add_argument("--years", type=float, default=2.0, help="years of healthy records per structure")
    parser.add_argument("--drifts", type=int, default=200, help="structures per drift rate")
    parser.add_argument("--rates", type=float, nargs="+", default=[0.5, 0.05], help="drift rates [%% a day]")
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    healthy = healthy_study(args.structures, args.years, args.seed)
    drifts = [drift_study(args.drifts, rate, max(10.0, 2.0 / rate), args.seed) for rate in args.rates]
    print(report(healthy, drifts, args.seed))


if __name__ == "__main__":
    main()
