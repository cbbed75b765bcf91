"""The refinement loop on the measured benchmarks, each by its own protocol (shared/data/README.md).

For every benchmark and output it prints the free-run RMS on the test records of

- the best linear output-error model: the linear orders :func:`models.refinement.choose_linear`
  picks on the estimation records' check blocks, the parameters then refined by output error on
  all the estimation records;
- the declared model (least squares) and the refined one, after the loop;
- the refined structure's free run over the estimation records' check parts, beside the noise
  between their periods where they repeat their excitation (:mod:`models.periods`);

beside the figures published for the benchmark, and the time the loop took. Run from the
project root (``--only silverbox`` etc. for one benchmark; ``--jobs`` benchmarks at once, each in
its own process, the longest first: about 40 minutes with two on 2 cores, F-16's accelerations
2 and 3 taking most of it)::

    .venv/bin/python -m bench.measured [--only NAME] [--jobs N]

Protocols: Silverbox estimates on samples [40650, 105712) of SNLS80mV and tests on the arrow
[100, 40575), each free run started from 50 measured samples; Wiener–Hammerstein estimates on
the ten multisine realisations and tests on the test file's multisine and swept sine; F-16
estimates on the sine sweeps of levels 3, 5 and 7 together and tests on levels 2, 4 and 6.

``--only f16-multisine`` runs F-16's other excitation by the same split: the full-grid multisines
of levels 3, 5 and 7, tested on 2, 4 and 6, every record used whole (the loop fits through the
first period, which holds the transient) and each test scored after its first period. The loop
was not developed on them; they are not part of the default run.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from functools import partial

import numpy as np
from rich.console import Console
from rich.progress import track
from rich.table import Table

from harness.prerequisites import DATA_DIR
from models.assessment import assess
from models.checking import SETTLED_EVALUATIONS
from models.effects import linear_terms
from models.errors import InputError
from models.output_error import fit_output_error
from models.refinement import Refinement, choose_linear, refine_records
from models.scoring import fit_model
from models.terms import Term, max_lag
from recordfiles.reader import SILVERBOX, Layout, read_record, read_record_set

Records = list[tuple[np.ndarray, np.ndarray]]
F16_PERIOD = 8192  # samples of one period of F-16's multisines; the first holds the transient


@dataclass(frozen=True)
class Benchmark:
    name: str
    estimation: Records
    tests: dict[str, tuple[np.ndarray, np.ndarray]]
    declared: tuple[Term, ...] | None
    initial: int
    published: str
    transient: int = 0  # samples of each test record run through but not scored


def silverbox(declared: tuple[Term, ...] | None, label: str) -> Benchmark:
    record = read_record(DATA_DIR / "silverbox" / "SNLS80mV.csv", SILVERBOX)
    x, y = record.x, record.y
    return Benchmark(
        f"Silverbox, {label}",
        [(x[40650:105712], y[40650:105712])],
        {"arrow": (x[100:40575], y[100:40575])},
        declared,
        50,
        "linear ARX 14–17 mV; cubic 1.5–2 mV; FROLS 4.15 mV; best a few tenths of a mV",
    )


def wiener_hammerstein() -> Benchmark:
    # The files hold their realisations side by side: u and y name groups, one record a pair.
    folder = DATA_DIR / "wiener-hammerstein"
    estimation = read_record_set(folder / "WH_EstimationExample.csv", Layout("u", "y"))
    (_, multisine), (_, swept) = read_record_set(folder / "WH_TestDataset.csv", Layout("u", "y"))
    return Benchmark(
        "Wiener–Hammerstein, orders chosen",
        [(r.x, r.y) for _, r in estimation],
        {"multisine": (multisine.x, multisine.y), "swept sine": (swept.x, swept.y)},
        None,
        0,
        "issue 14: linear(6,6) by least squares 47 mV, by output error 34 mV",
    )


def f16(output: int, multisine: bool = False) -> Benchmark:
    """F-16's benchmark by its split, on the sine sweeps or on the full-grid multisines (their
    first period holds the transient: the tests are scored after it)."""
    folder = DATA_DIR / "f16-gvt"
    layout = Layout("Force", f"Acceleration{output}")

    def level(number: int, suffix: str = "") -> tuple[np.ndarray, np.ndarray]:
        if multisine:
            record = read_record(folder / f"F16Data_FullMSine_Level{number}{suffix}.csv", layout)
        else:
            record = read_record(folder / f"F16Data_SineSw_Level{number}{suffix}.mat", layout)
        return record.x, record.y

    return Benchmark(
        f"F-16 acceleration {output}{', multisine' if multisine else ''}, orders chosen",
        [level(3), level(5), level(7)],
        {f"level {n}": level(n, "_Validation") for n in (2, 4, 6)},
        None,
        0,
        "none in shared/data",
        F16_PERIOD if multisine else 0,
    )


def best_linear(benchmark: Benchmark) -> tuple[tuple[int, int, int], dict[str, float]]:
    """The linear output-error model of the orders the loop chooses, judged on each test record."""
    orders, terms = choose_linear(benchmark.estimation)
    model, _ = fit_model(benchmark.estimation, terms, 0, max_lag(terms))
    try:
        model = fit_output_error(model, benchmark.estimation, SETTLED_EVALUATIONS).model
    except InputError:  # its least-squares start diverges: output error cannot start from it
        return orders, dict.fromkeys(benchmark.tests, np.inf)
    return orders, {
        name: assess(model, x, y, benchmark.initial, transient=benchmark.transient).free_run_rms
        for name, (x, y) in benchmark.tests.items()
    }


def rows(build: Callable[[], Benchmark]) -> list[tuple[str, ...]]:
    """The table's rows for one benchmark: its best linear model, then the loop, timed."""
    benchmark = build()
    orders, linear = best_linear(benchmark)
    started = time.perf_counter()
    report = refine_records(
        benchmark.estimation,
        list(benchmark.tests.values()),
        benchmark.declared,
        benchmark.initial,
        transient=benchmark.transient,
    )
    seconds = time.perf_counter() - started
    result = report.refinement
    effects = ", ".join(f"{s.added.name} ({s.criterion})" for s in result.kept if s.added) or "none"
    if result.effects_withdrawn:
        effects = f"withdrawn: {', '.join(result.effects_withdrawn)}; kept: {effects}"
    table = []
    for index, (name, comparison) in enumerate(zip(benchmark.tests, report.tests, strict=True)):
        first = index == 0
        table.append(
            (
                benchmark.name if first else "",
                name,
                f"{linear[name]:.4g} {orders}",
                f"{comparison.before.free_run_rms:.4g}"
                + (f" {result.orders}" if first and result.orders else ""),
                f"{comparison.after.free_run_rms:.4g} ({result.estimator})"
                if first
                else f"{comparison.after.free_run_rms:.4g}",
                effects if first else "",
                _check_and_floor(result) if first else "",
                f"{seconds:.0f} s" if first else "",
                benchmark.published if first else "",
            )
        )
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--only", choices=["silverbox", "wh", "f16", "f16-multisine"], help="one benchmark only"
    )
    parser.add_argument("--jobs", type=int, default=1, help="benchmarks run at once, each in a process")
    arguments = parser.parse_args()
    only = arguments.only
    # Longest first, so that the processes finish together; the table keeps this order.
    builders: list[Callable[[], Benchmark]] = []
    if only in (None, "f16"):
        builders += [partial(f16, output) for output in (3, 2, 1)]
    if only == "f16-multisine":
        builders += [partial(f16, output, multisine=True) for output in (3, 2, 1)]
    if only in (None, "wh"):
        builders.append(wiener_hammerstein)
    if only in (None, "silverbox"):
        builders += [
            partial(silverbox, linear_terms(4, 4), "from linear:4,4"),
            partial(silverbox, linear_terms(10, 10), "from linear:10,10"),
            partial(silverbox, None, "orders chosen"),
        ]
    table = Table(title="Free-run RMS on the test records (output units: V or m/s²)")
    for column in (
        "benchmark",
        "test",
        "best linear OE",
        "declared",
        "refined",
        "effects",
        "check / noise floor",
        "loop",
        "published",
    ):
        table.add_column(column)
    console = Console(width=220)
    with ProcessPoolExecutor(max(arguments.jobs, 1)) as pool:
        running = [pool.submit(rows, build) for build in builders]
        for _ in track(as_completed(running), total=len(running), description="benchmarks", console=console):
            pass
    for job in running:
        for row in job.result():
            table.add_row(*row)
    console.print(table)


def _check_and_floor(result: Refinement) -> str:
    """The refined structure's free-run RMS over the check records and, when they repeat their
    excitation, the noise between their periods: the least any model can leave there."""
    floor = result.noise_floor
    if floor is None:
        return f"{result.check_rms:.4g} / (no periods)"
    return f"{result.check_rms:.4g} / {floor.rms:.4g} ± {floor.standard_error:.1g}"


if __name__ == "__main__":
    main()
