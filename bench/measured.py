"""The refinement loop on the measured benchmarks, each by its own protocol (shared/data/README.md).

For every benchmark and output it prints the free-run RMS on the test records of

- the best linear output-error model: the loop's start, of the linear orders it chose (where a
  structure is declared, those :func:`models.refinement.choose_linear` picks on the estimation
  records' check blocks), the parameters refined by output error on all the estimation records;
- the declared model (least squares) and the refined one, after the loop;
- the refined structure's free run over the estimation records' check parts (in output units),
  beside the noise between their periods where they repeat their excitation (:mod:`models.periods`);
- the refined model's terms (and moving-average noise terms);

beside the figures published for the benchmark, and the time the loop took. Run from the
project root (``--only silverbox`` etc. for one benchmark, repeated for several; ``--jobs``
benchmarks at once, each in its own process, the longest first: about 40 minutes with two on 2
cores, F-16's accelerations 2 and 3 taking most of it)::

    .venv/bin/python -m bench.measured [--only NAME ...] [--jobs N]

Protocols: Silverbox estimates on samples [40650, 105712) of SNLS80mV and tests on the arrow
[100, 40575) and on the whole of Schroeder80mV, each free run started from 50 measured
samples; Wiener–Hammerstein estimates on the ten multisine realisations and tests on the test
file's multisine and swept sine; F-16 estimates on the sine sweeps of levels 3, 5 and 7
together and tests on levels 2, 4 and 6.
The coupled electric drives (both experiments of DATAUNIF.csv, (u11, z11) and (u12, z12))
estimate on each record's first 400 samples and test on its last 100, the free run started from
the 4 measured samples before them; a model that looks further back is started from as many,
and the test's name says so. Bouc–Wen trains on BW_train_multisine.csv and tests on both
official test signals, each read as published: u and y in MAT files of their own. The multisine
test is one period of its excitation in steady state (the system is not at rest at its first
sample), and a model's free run from those samples starts its hysteretic variable at rest: its
row is followed by the same period scored in steady state, the period run through once before it
is scored, as the PNLSS models of the benchmark are scored on it (pyvib's Bouc–Wen example,
after Noël's code: ``simulate(uval, T1=npp)``).

The DC motor/generator follows SysIdentPy's case studies ("Electromechanical System
Identification - Overview" and "- MetaMSS" in the documentation of wilsonrljr/sysidentpy):
both files decimated by plain slicing, ``iloc[::500]`` (no anti-aliasing filter;
1000 samples), split in halves by ``np.split``, the first estimating and the second testing; the
free run (``predict`` with ``steps_ahead=None``) starts from the test half's first ``max_lag``
measured outputs, and the relative root squared error ‖y − ŷ‖/‖y − ȳ‖ is taken after them. (The
Overview's older text reads the files with pandas' default header, which drops the first sample,
and scores the whole half; the MetaMSS page reads them with ``header=None``, as here.) Here every
model, narxwatch's and SysIdentPy's, is scored after the same 5 samples, the case studies' lags.
SysIdentPy 0.9 runs in the same script on the same split, in a subprocess of .venv-bench
(``make .venv-bench/.installed``; SysIdentPy caps numpy below narxwatch's): FROLS with ylag 2,
xlag 2, degree 2 and BIC, and the two case studies' settings: FROLS with ylag 5, xlag 5, degree 2,
BIC over up to 100 terms and recursive least squares (reported 0.0568), and MetaMSS with ylag 5,
xlag 5, degree 2, recursive least squares (λ 0.95) on standardised signals, seed 42 (reported
0.0314). Its rows give the RRSE, the terms and the seconds of fit and free run.

``--only coupled-drives-prbs`` runs the drives' three PRBS records (DATAPRBS.csv: u1, u2 and u3
of amplitudes 1, 1.5 and 0.5) split as the uniform ones; they are further data with no protocol
or published figures, not part of the default run.

``--only f16-multisine`` runs F-16's other excitation by the same split: the full-grid multisines
of levels 3, 5 and 7, tested on 2, 4 and 6, every record used whole (the loop fits through the
first period, which holds the transient) and each test scored after its first period. The loop
was not developed on them; they are not part of the default run.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import textwrap
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from functools import partial
from pathlib import Path

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
from models.refinement import Refinement, choose_linear, compare, refine_records
from models.scoring import fit_model
from models.terms import Term, max_lag
from recordfiles.reader import SILVERBOX, Layout, read_record, read_record_set, read_split_record

Records = list[tuple[np.ndarray, np.ndarray]]
F16_PERIOD = 8192  # samples of one period of F-16's multisines; the first holds the transient
# Coupled drives: the first 400 samples of each record estimate, the last 100 test, each free run
# started from the 4 measured samples before them.
DRIVES_ESTIMATION, DRIVES_INITIAL = 400, 4
# DC motor/generator: SysIdentPy's case study keeps every 500th sample; its models look back 5
# samples at most, and each free run is scored after the first 5 measured outputs that start it.
DC_DECIMATION, DC_INITIAL = 500, 5
ONLY = (
    "silverbox",
    "wh",
    "f16",
    "f16-multisine",
    "bouc-wen",
    "dc-motor",
    "coupled-drives",
    "coupled-drives-prbs",
)
# The other excitations of F-16 and the drives run when named only.
BY_DEFAULT = tuple(name for name in ONLY if name not in ("f16-multisine", "coupled-drives-prbs"))
BENCH_PYTHON = Path(__file__).resolve().parents[1] / ".venv-bench" / "bin" / "python"


@dataclass(frozen=True)
class Benchmark:
    name: str
    estimation: Records
    tests: dict[str, tuple[np.ndarray, np.ndarray]]
    declared: tuple[Term, ...] | None
    initial: int
    published: str
    transient: int = 0  # samples of each test record run through but not scored
    # Figures as the relative root squared error RRSE = ‖y − ŷ‖/‖y − ȳ‖ over the scored samples
    # (the free-run RMS over the test output's standard deviation), as SysIdentPy scores its cases.
    relative: bool = False
    # Another library's models on the same split: their rows of the table.
    peers: Callable[[Benchmark], list[tuple[str, ...]]] | None = None
    # Tests that are one period of a periodic excitation in steady state: scored besides in steady
    # state, the period run through once before it is scored, where the free run from the record's
    # first samples starts a state the model holds beside its lags (a hysteretic variable) at rest.
    steady_state: tuple[str, ...] = ()

    def scored(self) -> list[tuple[str, np.ndarray, np.ndarray, int]]:
        """Each test as it is scored: its name, x, y and the samples run through first; then each
        steady-state test again, its period repeated and the first run through."""
        plain = [(name, x, y, self.transient) for name, (x, y) in self.tests.items()]
        return plain + [
            (f"{name}, steady state", np.tile(x, 2), np.tile(y, 2), len(y))
            for name, (x, y) in self.tests.items()
            if name in self.steady_state
        ]

    def figure(self, test: str, rms: float, lag: int) -> float:
        """The table's figure for a free-run RMS on ``test`` of a model looking ``lag`` samples back:
        the RMS itself, or the RRSE over the samples it was scored on
        (:func:`models.assessment.assess`)."""
        if not self.relative:
            return rms
        _, y = self.tests[test]
        return rms / float(np.std(y[max(self.initial, lag, self.transient) :]))


def silverbox(declared: tuple[Term, ...] | None, label: str) -> Benchmark:
    """Silverbox by the official split, tested on the arrow and on Schroeder80mV whole: a record
    of its own, another excitation (a Schroeder-phase multisine), on which a model that fits
    the arrow can still fail."""
    record = read_record(DATA_DIR / "silverbox" / "SNLS80mV.csv", SILVERBOX)
    schroeder = read_record(DATA_DIR / "silverbox" / "Schroeder80mV.csv", SILVERBOX)
    x, y = record.x, record.y
    return Benchmark(
        f"Silverbox, {label}",
        [(x[40650:105712], y[40650:105712])],
        {"arrow": (x[100:40575], y[100:40575]), "Schroeder80mV": (schroeder.x, schroeder.y)},
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


def coupled_drives(column: int, prbs: bool = False) -> Benchmark:
    """One experiment of the coupled electric drives by the benchmark's protocol: (u1k, z1k) of
    DATAUNIF.csv or, with ``prbs``, (uk, zk) of DATAPRBS.csv (further data, no protocol of its own:
    split alike)."""
    file, x, y = (
        ("DATAPRBS.csv", f"u{column}", f"z{column}")
        if prbs
        else ("DATAUNIF.csv", f"u1{column}", f"z1{column}")
    )
    record = read_record(DATA_DIR / "coupled-drives" / file, Layout(x, y))
    start = len(record.y) - 100 - DRIVES_INITIAL
    published = {
        1: "polynomial NARX 0.10, GP-NARX 0.102, SysIdentPy 0.103, best 0.115; LTI 0.224, ARX 0.291",
        2: "polynomial NARX 0.141, GP-NARX 0.090, SysIdentPy 0.107, best 0.074; LTI 0.384, ARX 0.331",
    }
    experiment = f"PRBS ±{np.max(np.abs(record.x)):g}" if prbs else f"test {column}"
    return Benchmark(
        f"Coupled drives, {experiment}, orders chosen",
        [(record.x[:DRIVES_ESTIMATION], record.y[:DRIVES_ESTIMATION])],
        {"last 100": (record.x[start:], record.y[start:])},
        None,
        DRIVES_INITIAL,
        "none (further data)" if prbs else published[column],
    )


def bouc_wen() -> Benchmark:
    """Trained on the multisine record, tested on both official test signals, read as published:
    u and y in MAT files of their own."""
    folder = DATA_DIR / "bouc-wen"
    training = read_record(folder / "BW_train_multisine.csv", Layout("u", "y"))

    def test(name: str) -> tuple[np.ndarray, np.ndarray]:
        record = read_split_record(
            folder / f"uval_{name}.mat", folder / f"yval_{name}.mat", Layout(f"uval_{name}", f"yval_{name}")
        )
        return record.x, record.y

    return Benchmark(
        "Bouc–Wen, orders chosen",
        [(training.x, training.y)],
        {"multisine": test("multisine"), "sine sweep": test("sinesweep")},
        None,
        0,
        "multisine: PNLSS 1.87e-5 m, dynoNet 4.52e-5 m, NFIR 16.3e-5 m",
        steady_state=("multisine",),
    )


def dc_motor() -> Benchmark:
    """SysIdentPy's DC motor/generator case study, its split and its score (module docstring)."""
    folder = DATA_DIR / "dc-motor-generator"
    # One number a line and no header: the record readers want named columns.
    x, y = (np.loadtxt(folder / name)[::DC_DECIMATION] for name in ("x_cc.csv", "y_cc.csv"))
    half = len(y) // 2
    return Benchmark(
        "DC motor/generator, orders chosen (RRSE)",
        [(x[:half], y[:half])],
        {"second half": (x[half:], y[half:])},
        None,
        DC_INITIAL,
        "SysIdentPy's docs: FROLS 0.0568, MetaMSS 0.0314, entropic regression 0.0328",
        relative=True,
        peers=sysidentpy_rows,
    )


# SysIdentPy 0.9's models on a benchmark's split, run in .venv-bench (SysIdentPy caps numpy below
# the version narxwatch runs on): the FROLS issue 49 compared with, then the settings of
# SysIdentPy's own DC motor/generator case studies (module docstring). Each prints one JSON line:
# its name, seconds (fit and free run), terms, lag and free run over the test record, started from
# the record's first measured outputs as SysIdentPy's predict does.
SYSIDENTPY = textwrap.dedent(
    """
    import io, json, sys, time
    import numpy as np
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.model_structure_selection import FROLS, MetaMSS
    from sysidentpy.parameter_estimation import RecursiveLeastSquares

    data = np.load(io.BytesIO(sys.stdin.buffer.read()))
    x_fit, y_fit, x_test, y_test = (data[k].reshape(-1, 1) for k in ("x_fit", "y_fit", "x_test", "y_test"))
    settings = [
        ("FROLS ylag 2, xlag 2, degree 2, BIC", False, lambda: FROLS(
            order_selection=True, ylag=2, xlag=2, info_criteria="bic", basis_function=Polynomial(degree=2))),
        ("FROLS ylag 5, xlag 5, degree 2, BIC, recursive LS (its case study)", False, lambda: FROLS(
            order_selection=True, n_info_values=100, ylag=5, xlag=5, info_criteria="bic", err_tol=None,
            estimator=RecursiveLeastSquares(), basis_function=Polynomial(degree=2))),
        ("MetaMSS ylag 5, xlag 5, degree 2, standardised (its case study)", True, lambda: MetaMSS(
            xlag=5, ylag=5, estimator=RecursiveLeastSquares(lam=0.95, delta=0.01), maxiter=5, n_agents=15,
            basis_function=Polynomial(degree=2), random_state=42)),
    ]
    settings[0][2]().fit(X=x_fit, y=y_fit)  # the first fit imports and compiles: not timed
    for name, standardised, build in settings:
        (mx, sx), (my, sy) = [(s.mean(), s.std()) if standardised else (0.0, 1.0) for s in (x_fit, y_fit)]
        started = time.perf_counter()
        model = build()
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            model.fit(X=(x_fit - mx) / sx, y=(y_fit - my) / sy)
        yhat = model.predict(X=(x_test - mx) / sx, y=(y_test - my) / sy) * sy + my
        seconds = time.perf_counter() - started
        terms, lag = len(model.final_model), int(model.max_lag)
        print(json.dumps(dict(name=name, seconds=seconds, terms=terms, lag=lag, yhat=yhat.ravel().tolist())))
    """
)


def sysidentpy_rows(benchmark: Benchmark) -> list[tuple[str, ...]]:
    """SysIdentPy's models (``SYSIDENTPY``) fitted on the benchmark's estimation record and run
    free over its test record as SysIdentPy's ``predict`` runs them (from the record's first
    ``max_lag`` measured outputs), scored as narxwatch's are: after ``initial`` samples (or the
    model's lag, if longer)."""
    ((x_fit, y_fit),) = benchmark.estimation
    ((test, (x_test, y_test)),) = benchmark.tests.items()
    if not BENCH_PYTHON.exists():
        return [row("  SysIdentPy not run: build .venv-bench (make .venv-bench/.installed)")]
    data = io.BytesIO()
    np.savez(data, x_fit=x_fit, y_fit=y_fit, x_test=x_test, y_test=y_test)
    done = subprocess.run(
        [str(BENCH_PYTHON), "-c", SYSIDENTPY],
        input=data.getvalue(),
        capture_output=True,
        env=os.environ | {"OPENBLAS_NUM_THREADS": "1"},
    )
    if done.returncode:  # said in the table, so that the other benchmarks' rows still print
        *_, last = done.stderr.decode().strip().splitlines() or ["(nothing on stderr)"]
        return [row(f"  SysIdentPy failed: {last}")]
    table = []
    for line in done.stdout.decode().splitlines():
        if not line.startswith("{"):
            continue
        run = json.loads(line)
        start = max(benchmark.initial, run["lag"])
        rms = float(np.sqrt(np.mean((np.asarray(run["yhat"])[start:] - y_test[start:]) ** 2)))
        table.append(
            row(
                f"  SysIdentPy 0.9 {run['name']}",
                test,
                refined=f"{benchmark.figure(test, rms, run['lag']):.4g}",
                terms=str(run["terms"]),
                loop=f"{run['seconds']:.2f} s",
            )
        )
    return table


COLUMNS = (
    "benchmark",
    "test",
    "best linear OE",
    "declared",
    "refined",
    "effects",
    "terms",
    "check / noise floor",
    "loop",
    "published",
)


def row(
    benchmark: str,
    test: str = "",
    linear: str = "",
    declared: str = "",
    refined: str = "",
    effects: str = "",
    terms: str = "",
    check: str = "",
    loop: str = "",
    published: str = "",
) -> tuple[str, ...]:
    """A row of the table, its cells in the order of ``COLUMNS``."""
    return (benchmark, test, linear, declared, refined, effects, terms, check, loop, published)


def best_linear(
    benchmark: Benchmark, result: Refinement
) -> tuple[tuple[int, int, int], int, dict[str, float]]:
    """The linear output-error model of the orders the loop chose (``result``'s start), its lag,
    and its figure on each test record; where a structure was declared, of the orders
    :func:`choose_linear` picks on the estimation records. The loop chooses its orders on the
    records without the tails it holds out, and on F-16's sweeps, which fall in frequency so
    that their tails hold the bottom of the band, those are smaller orders than whole sweeps ask
    for: chosen here again on whole records, the column would not be the start the refined model
    was judged against."""
    if result.orders is not None:
        orders, terms = result.orders, result.declared.terms
    else:
        orders, terms = choose_linear(benchmark.estimation)
    model, _ = fit_model(benchmark.estimation, terms, 0, max_lag(terms))
    try:
        model = fit_output_error(model, benchmark.estimation, SETTLED_EVALUATIONS).model
    except InputError:  # its least-squares start diverges: output error cannot start from it
        return orders, model.max_lag, dict.fromkeys([name for name, *_ in benchmark.scored()], np.inf)
    return (
        orders,
        model.max_lag,
        {
            name: benchmark.figure(
                name, assess(model, x, y, benchmark.initial, transient=transient).free_run_rms, model.max_lag
            )
            for name, x, y, transient in benchmark.scored()
        },
    )


def rows(build: Callable[[], Benchmark]) -> list[tuple[str, ...]]:
    """The table's rows for one benchmark: the loop, timed, then its start's best linear model,
    then any other library's models on the same split."""
    benchmark = build()
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
    orders, linear_lag, linear = best_linear(benchmark, result)
    steady = [
        compare(result, benchmark.estimation, x, y, benchmark.initial, None, 0, transient)
        for *_, x, y, transient in benchmark.scored()[len(benchmark.tests) :]
    ]
    effects = ", ".join(f"{s.added.name} ({s.criterion})" for s in result.kept if s.added) or "none"
    if result.effects_withdrawn:
        effects = f"withdrawn: {', '.join(result.effects_withdrawn)}; kept: {effects}"
    terms = f"{len(result.refined.terms)}" + (f" + {len(result.noise)} noise" if len(result.noise) else "")
    lags = (linear_lag, result.declared.max_lag, result.refined.max_lag)
    table = []
    names = [name for name, *_ in benchmark.scored()]
    for index, (name, comparison) in enumerate(zip(names, [*report.tests, *steady], strict=True)):
        first = index == 0
        before = benchmark.figure(name, comparison.before.free_run_rms, result.declared.max_lag)
        after = benchmark.figure(name, comparison.after.free_run_rms, result.refined.max_lag)
        table.append(
            row(
                benchmark.name if first else "",
                name + _started_later(benchmark, max(lags)),
                linear=f"{linear[name]:.4g} {orders}",
                declared=f"{before:.4g}" + (f" {result.orders}" if first and result.orders else ""),
                refined=f"{after:.4g} ({result.estimator})" if first else f"{after:.4g}",
                effects=effects if first else "",
                terms=terms if first else "",
                check=_check_and_floor(result) if first else "",
                loop=f"{seconds:.0f} s" if first else "",
                published=benchmark.published if first else "",
            )
        )
    return table + (benchmark.peers(benchmark) if benchmark.peers else [])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--only", choices=ONLY, action="append", help="this benchmark only (repeat for several)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="benchmarks run at once, each in a process")
    arguments = parser.parse_args()
    only = set(arguments.only or BY_DEFAULT)
    # Longest first, so that the processes finish together; the table keeps this order.
    builders: list[Callable[[], Benchmark]] = []
    if "f16" in only:
        builders += [partial(f16, output) for output in (3, 2, 1)]
    if "f16-multisine" in only:
        builders += [partial(f16, output, multisine=True) for output in (3, 2, 1)]
    if "bouc-wen" in only:
        builders.append(bouc_wen)
    if "wh" in only:
        builders.append(wiener_hammerstein)
    if "silverbox" in only:
        builders += [
            partial(silverbox, linear_terms(4, 4), "from linear:4,4"),
            partial(silverbox, linear_terms(10, 10), "from linear:10,10"),
            partial(silverbox, None, "orders chosen"),
        ]
    if "dc-motor" in only:
        builders.append(dc_motor)
    if "coupled-drives" in only:
        builders += [partial(coupled_drives, column) for column in (1, 2)]
    if "coupled-drives-prbs" in only:
        builders += [partial(coupled_drives, column, prbs=True) for column in (1, 2, 3)]
    table = Table(title="Free-run RMS on the test records (output units; RRSE where named)")
    for column in COLUMNS:
        table.add_column(column)
    console = Console(width=220)
    with ProcessPoolExecutor(max(arguments.jobs, 1)) as pool:
        running = [pool.submit(rows, build) for build in builders]
        for _ in track(as_completed(running), total=len(running), description="benchmarks", console=console):
            pass
    for job in running:
        for each in job.result():
            table.add_row(*each)
    console.print(table)


def _started_later(benchmark: Benchmark, lag: int) -> str:
    """Where a protocol starts each free run from ``initial`` measured outputs and a model looks
    further back, :func:`models.assessment.assess` starts it from ``lag`` and scores the rest:
    said beside the test's name, since fewer samples are scored than the protocol's."""
    if benchmark.initial == 0 or lag <= benchmark.initial:
        return ""
    return f" (started from {lag} samples)"


def _check_and_floor(result: Refinement) -> str:
    """The refined structure's free-run RMS over the check records and, when they repeat their
    excitation, the noise between their periods: the least any model can leave there."""
    floor = result.noise_floor
    if floor is None:
        return f"{result.check_rms:.4g} / (no periods)"
    return f"{result.check_rms:.4g} / {floor.rms:.4g} ± {floor.standard_error:.1g}"


if __name__ == "__main__":
    main()
