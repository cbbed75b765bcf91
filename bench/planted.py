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
chosen. Then clean records, nothing planted, each seed three ways: the linear structure (the rig
with its cubic spring taken out, k3 = 0; its 800 N unmeasured force, no sensor noise) with
nothing declared, where any effect added is one the system does not have; the rig as it is with
nothing declared, where its own cubic spring is the one effect to find (a power law of the output
whose exponent the search left at the top of its range is counted apart, as the spring's
stand-in); and the rig from its structure, where nothing is left to add. For each, how many
records the loop left as they should be, and what it added to the others. ``--seeds 0`` runs the
clean records alone.

Run from the project root; develop on seeds below 1000 (``--first-seed 1``), report on
held-out seeds (the default first seed; seeds 5000–5002, 7000–7001 and 8000–8111 have been reported on
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

from models.effects import STIFFNESS_EXPONENTS
from models.refinement import refine
from models.terms import Term
from models.validation import validate
from simulator.physics import PhysicalParameters
from simulator.simulate import Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS

TEST = 4000  # samples of each held-out record
TEST_SEEDS = 50_000  # a held-out record's seed: its estimation record's plus this
HELD_OUT_SEEDS = 8312  # the first seed of the report; development used seeds below 1000
PLANTED_FORCE = 200.0  # N of unmeasured force beside a planted effect, as the tests plant them
RIG_FORCE = 800.0  # N of unmeasured force on the rig as it is: the clean records'
# The clean records: the rig as it is, and the linear structure it is without its cubic spring
# (its unmeasured force and sensors the rig's), on which nothing declared has nothing to find.
RIG = Scenario(disturbance_std=RIG_FORCE)
LINEAR_RIG = Scenario(params=PhysicalParameters(k3=0.0), disturbance_std=RIG_FORCE)
# The rig's own cubic spring on the measured mass (SPEC §2): with nothing declared, an effect the
# loop may rightly name before the planted one.
RIG_SPRING = "cubic_stiffness"
# A power law of the output's stiffness with its exponent at the top of the range searched: the
# data asked for a law at least that steep, and the cube is the rig's. Counted apart, as the
# spring's stand-in, on the rig's clean records.
LAW_AT_THE_TOP = f"power_law_stiffness p={STIFFNESS_EXPONENTS[1]:g}"


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
        """Whether the planted effect was named first, or next after the rig's own spring (which
        may enter over several rounds, each adding lags of it)."""
        rest = self.named
        while rest[:1] == (RIG_SPRING,):
            rest = rest[1:]
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


def named(name: str, terms: tuple[str, ...]) -> str:
    """An effect's name, a power law's with the exponent found (every lag of a law shares it)."""
    if name != "power_law_stiffness" or not terms:
        return name
    return f"{name} p={Term.parse(terms[0]).factors[0].parameter:g}"


@dataclass(frozen=True)
class Clean:
    """The effects the loop added to the clean records of one seed: the linear structure's with
    nothing declared, the rig's with nothing declared, and the rig's from its structure."""

    linear: tuple[str, ...]
    rig: tuple[str, ...]
    rig_declared: tuple[str, ...]


def run_clean(samples: int, seed: int) -> Clean:
    """The loop on the clean records of one seed, the linear structure's and the rig's drawn
    alike (the same excitation and unmeasured force; the rig's cubic spring the one difference)."""
    linear = simulate(LINEAR_RIG, samples, seed)
    rig = simulate(RIG, samples, seed)

    def added(x: np.ndarray, y: np.ndarray, declared: str | None) -> tuple[str, ...]:
        return tuple(named(effect.name, effect.terms) for effect in refine([(x, y)], declared).effects_added)

    return Clean(added(linear.x, linear.y, None), added(rig.x, rig.y, None), added(rig.x, rig.y, EXACT_TERMS))


# The clean records' three counts: which of a seed's loops, what it may add and stay honest, and
# what stands in for that (counted apart).
CLEAN_CHECKS = (
    ("linear structure, nothing declared: nothing added", "linear", frozenset(), frozenset()),
    (
        "rig, nothing declared: nothing but the rig's own cubic spring added",
        "rig",
        frozenset({RIG_SPRING}),
        frozenset({LAW_AT_THE_TOP}),
    ),
    ("rig declared: nothing added", "rig_declared", frozenset(), frozenset()),
)


def clean_lines(clean: list[Clean], samples: int) -> list[str]:
    """The three counts of the clean records, each with every set of effects added and how often."""
    lines = []
    for label, loop, allowed, stand_ins in CLEAN_CHECKS:
        added = [getattr(run, loop) for run in clean]
        honest = sum(set(effects) <= allowed for effects in added)
        standing_in = sum(set(effects) <= allowed | stand_ins for effects in added) - honest
        seen = Counter(" + ".join(effects) for effects in added if effects)
        lines.append(
            f"clean records ({samples} samples, {RIG_FORCE:.0f} N force), {label} in {honest}/{len(clean)}"
            + (
                f" (and {standing_in} with {' or '.join(sorted(stand_ins))} in its place)"
                if stand_ins
                else ""
            )
            + (f"; added: {dict(seen)}" if seen else "")
        )
    return lines


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
    clean: list[Clean] = []
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
    if clean:
        for line in clean_lines(clean, arguments.samples[0]):
            console.print(line)


if __name__ == "__main__":
    main()
