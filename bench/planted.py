"""Planted effects with nothing declared: is the planted effect named first, and does the loop's
model simulate held-out data nearly as well as the one refined from the rig's physics?

Each case plants one effect in the 2-DOF rig's records (the simulator's ``--effect``, sized as
the tests size them: every family a simulated effect plants, tests/test_effects_output.py, and
the six undeclared effects of tests/test_refinement.py) and runs :func:`models.refinement.refine` twice on
the same estimation record: with nothing declared (the linear orders the loop chooses), and from
the rig's structure (SPEC §2, ``--declared 2dof``). Both refined models run free over a held-out
record simulated from another seed; a sinusoidal force has a random phase a record, so the
periodic disturbance's held-out part is its own record's continuation. For each case and size
the table gives how often the planted effect was named first (and first once the rig's own
cubic spring, an effect to find when nothing is declared, is set aside), the median and worst
ratio of the held-out free-run RMS nothing-declared / rig-declared, and the linear orders
chosen. Then the loop on clean records of the rig (its 800 N unmeasured force), with nothing
declared and from the rig's structure: how many it left alone.

Run from the project root; develop on seeds below 1000 (``--first-seed 1``), report on
held-out seeds (the default first seed; seeds 5000–5002, 7000–7001 and 8000–8011 have been reported on
and are no longer held out)::

    .venv/bin/python -m bench.planted [--seeds 3] [--samples 1600 4000] [--clean 100] [--jobs 2]
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from models.refinement import refine
from models.validation import validate
from simulator.simulate import Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS

TEST = 4000  # samples of each held-out record
TEST_SEEDS = 50_000  # a held-out record's seed: its estimation record's plus this
HELD_OUT_SEEDS = 8012  # the first seed of the report; development used seeds below 1000
PLANTED_FORCE = 200.0  # N of unmeasured force beside a planted effect, as the tests plant them
RIG_FORCE = 800.0  # N of unmeasured force on the rig as it is: the clean records'
# The rig's own cubic spring on the measured mass (SPEC §2): with nothing declared, an effect the
# loop may rightly name before the planted one.
RIG_SPRING = "cubic_stiffness"


@dataclass(frozen=True)
class Case:
    """One planted effect: the family that should be named first, the simulator's spec, and the
    scenario that plants it."""

    family: str
    spec: str
    scenario: Scenario

    @property
    def periodic(self) -> bool:
        return bool(self.scenario.effects.sine_amplitude)


def planted(family: str, spec: str) -> Case:
    return Case(family, spec, Scenario(disturbance_std=PLANTED_FORCE, effects=Effects.parse([spec])))


CASES = [
    # The six undeclared effects of tests/test_refinement.py.
    planted("coulomb_friction", "coulomb2=300"),
    planted("quadratic_damping", "quadratic_damping2=2000"),
    planted("quadratic_stiffness", "quadratic_stiffness2=3e5"),
    planted("offset", "offset=0.02"),
    planted("periodic_disturbance", "sine=1000@12.5"),
    # Coloured force-sensor noise, the only noise: not an --effect but the scenario's noise colour.
    Case(
        "moving_average_noise",
        "x noise 800 N, colour 1.5…0.3",
        Scenario(x_noise_std=800.0, noise_colour=(1.5, 1.2, 0.9, 0.6, 0.3)),
    ),
    # Every family the simulator plants.
    planted("output_saturation", "sensor_range=0.08"),
    planted("power_law_damping", "power_damping2=1000"),
    planted("power_law_stiffness", "hertz_contact2=5e4"),
    planted("input_dead_zone", "dead_zone=10000"),
    planted("input_backlash", "backlash=5000"),
    planted("unmeasured_nonlinearity", "cubic_stiffness1=4e6"),
    planted("hysteresis", "hysteresis2=3e4"),
]


@dataclass(frozen=True)
class Run:
    """One record of one case refined twice: what the loop with nothing declared named and
    chose, and both refined models' held-out free-run RMS."""

    case: int
    samples: int
    seed: int
    named: tuple[str, ...]
    orders: tuple[int, int, int] | None
    free_run: float  # nothing declared
    rig_free_run: float  # from the rig's structure
    seconds: float

    @property
    def ratio(self) -> float:
        return self.free_run / self.rig_free_run if np.isfinite(self.free_run) else np.inf

    @property
    def first(self) -> bool:
        """Whether the planted effect was named first."""
        return bool(self.named) and self.named[0] == CASES[self.case].family

    @property
    def first_but_the_spring(self) -> bool:
        """Whether the planted effect was named first, or second after the rig's own spring."""
        rest = self.named[1:] if self.named[:1] == (RIG_SPRING,) else self.named
        return bool(rest) and rest[0] == CASES[self.case].family


def run_case(case: int, samples: int, seed: int) -> Run:
    """The loop with nothing declared and from the rig's structure on one planted record."""
    scenario = CASES[case].scenario
    if CASES[case].periodic:
        record = simulate(scenario, samples + TEST, seed)
        x, y = record.x[:samples], record.y[:samples]
        test, t0 = (record.x[samples:], record.y[samples:]), samples
    else:
        record, held_out = simulate(scenario, samples, seed), simulate(scenario, TEST, seed + TEST_SEEDS)
        x, y = record.x, record.y
        test, t0 = (held_out.x, held_out.y), 0
    started = time.perf_counter()
    found = refine([(x, y)], None)
    seconds = time.perf_counter() - started
    rig = refine([(x, y)], EXACT_TERMS)
    return Run(
        case,
        samples,
        seed,
        tuple(effect.name for effect in found.effects_added),
        found.orders,
        validate(found.refined, [test], t0=t0).free_run.rms,
        validate(rig.refined, [test], t0=t0).free_run.rms,
        seconds,
    )


def run_clean(samples: int, seed: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The effects the loop adds to a clean record of the rig with nothing declared and from the
    rig's structure. (The rig has a cubic spring: nothing declared, that is an effect to find.)"""
    record = simulate(Scenario(disturbance_std=RIG_FORCE), samples, seed)
    return tuple(
        tuple(effect.name for effect in refine([(record.x, record.y)], declared).effects_added)
        for declared in (None, EXACT_TERMS)
    )


def orders_text(runs: list[Run]) -> str:
    counts = Counter(run.orders for run in runs)
    return ", ".join(
        f"({n}, {n}, {d})" + (f" ×{count}" if count > 1 else "")
        for (n, _, d), count in sorted(counts.items())
        if n is not None
    )


def table(runs: list[Run]) -> Table:
    result = Table(title="Planted effects, nothing declared (free run: nothing declared / rig declared)")
    columns = (
        "planted",
        "family",
        "samples",
        "named first",
        "spring aside",
        "median",
        "worst",
        "orders",
        "instead",
        "s",
    )
    for column in columns:
        result.add_column(column)
    for index, case in enumerate(CASES):
        for samples in sorted({run.samples for run in runs}):
            group = [run for run in runs if run.case == index and run.samples == samples]
            if not group:
                continue
            first = [run for run in group if run.first]
            ratios = np.array([run.ratio for run in group])
            instead = Counter(run.named[0] if run.named else "nothing" for run in group if run not in first)
            result.add_row(
                case.spec,
                case.family,
                str(samples),
                f"{len(first)}/{len(group)}",
                f"{sum(run.first_but_the_spring for run in group)}/{len(group)}",
                f"{np.median(ratios):.3g}",
                f"{np.max(ratios):.3g}",
                orders_text(group),
                ", ".join(f"{name} ×{count}" for name, count in instead.items()),
                f"{np.median([run.seconds for run in group]):.0f}",
            )
    return result


def summary(runs: list[Run]) -> str:
    named = sum(run.first for run in runs)
    aside = sum(run.first_but_the_spring for run in runs)
    within = sum(run.ratio <= 2 for run in runs)
    return (
        f"named first: {named}/{len(runs)} ({100 * named / max(len(runs), 1):.0f} %); "
        f"first or after the rig's own spring: {aside}/{len(runs)}; "
        f"held-out free run within 2× of the rig-declared: {within}/{len(runs)}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="records a case and size")
    parser.add_argument(
        "--first-seed", type=int, default=HELD_OUT_SEEDS, help="the first record's seed (develop below 1000)"
    )
    parser.add_argument("--samples", type=int, nargs="+", default=[1600, 4000], help="estimation sizes")
    parser.add_argument("--clean", type=int, default=100, help="clean records (of the first size)")
    parser.add_argument("--only", nargs="+", help="only these families")
    parser.add_argument("--jobs", type=int, default=1, help="records refined at once, each in a process")
    arguments = parser.parse_args()
    cases = [i for i, case in enumerate(CASES) if not arguments.only or case.family in arguments.only]
    seeds = range(arguments.first_seed, arguments.first_seed + arguments.seeds)
    console = Console(width=200)
    runs: list[Run] = []
    clean: list[tuple[tuple[str, ...], tuple[str, ...]]] = []
    progress = Progress(
        TextColumn("{task.description:<16}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    )
    with progress, ProcessPoolExecutor(max(arguments.jobs, 1)) as pool:
        # The longest first, so that the processes finish together.
        jobs = [
            pool.submit(run_case, case, samples, seed)
            for samples in sorted(arguments.samples, reverse=True)
            for case in cases
            for seed in seeds
        ]
        clean_jobs = [
            pool.submit(run_clean, arguments.samples[0], seed)
            for seed in range(arguments.first_seed, arguments.first_seed + arguments.clean)
        ]
        task = progress.add_task("planted records", total=len(jobs))
        for job in as_completed(jobs):
            runs.append(job.result())
            progress.advance(task)
        task = progress.add_task("clean records", total=len(clean_jobs))
        for job in as_completed(clean_jobs):
            clean.append(job.result())
            progress.advance(task)
    console.print(table(runs))
    console.print(summary(runs))
    for index, start in enumerate(("nothing declared", "rig declared")):
        if clean:
            alone = sum(not named[index] for named in clean)
            added = Counter(named[index][0] for named in clean if named[index])
            console.print(
                f"clean records ({arguments.samples[0]} samples, {RIG_FORCE:.0f} N force), {start}: "
                f"nothing added in {alone}/{len(clean)}" + (f"; first added: {dict(added)}" if added else "")
            )


if __name__ == "__main__":
    main()
