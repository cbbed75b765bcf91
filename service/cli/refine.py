"""``narxwatch refine``: find the effects a model lacks and report the error before and after.

Two protocols. **Parts of one record** (one record, no ``--validate``; or ``--estimation``/
``--test`` given; or ``--format silverbox``, whose benchmark prescribes its split): the loop runs
on the estimation part (or parts, ``--estimation A:B,C:D``, fitted as records of their own: a
glitch between them is left out) and both models are judged on the test part, then on each
``--validate`` record whole. **Whole records** (several estimation records, or one with ``--validate``):
estimation on all of them at once (no lag crosses a record's boundary), each ``--validate``
record judged whole. ``--transient`` names the first samples of every record its transient:
records used whole are fitted through it and every free run starts at the record's start, at rest
with the structure, and is scored after it; on parts of one record, the parts count from its end.
Every record judged says how much of it lies outside the data fitted (:mod:`models.coverage`).
A file
holds one record, or one for each pair of signals when ``--x`` and ``--y`` name groups of as many
(:func:`recordfiles.reader.parse_record_set`).
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from rich.progress import SpinnerColumn, TextColumn, TimeElapsedColumn

from models.effects import linear_terms
from models.errors import InputError
from models.held_out import unseen_by
from models.kinks import kinked_laws_reason
from models.refinement import DEFAULT_ALPHA, Stage
from models.refinement_protocol import Loop, Refined, default_split, refine_parts, refine_whole
from models.regression import Workers
from models.terms import Term
from recordfiles.reader import DEFAULT_LAYOUT, SILVERBOX, Layout, read_record_set
from service.cli.console import stdout, transient_progress
from service.cli.memory import hold_freed_memory
from service.cli.modelfiles import RECORD_SET_HELP, RIG, XName, YName, common_rate, read_terms, signal_layout
from simulator.client.groups import expanded

# The Silverbox benchmark's official split (shared/data/README.md): estimation and arrow test,
# each test run started from 50 measured outputs.
SILVERBOX_ESTIMATION = (40650, 105712)
SILVERBOX_TEST = (100, 40575)
SILVERBOX_INITIAL = 50
SILVERBOX_UNIT = "V"  # both of its signals are voltages
# ``--declared`` naming SPEC §2's structure of the simulated 2-DOF rig.
# Each worker is a copy of this process: beyond a CPU's share, more only cost memory. More than
# one a CPU is allowed all the same, so that two workers run (slower) on a machine of one CPU.
JOBS_PER_CPU = 2

DECLARED_HELP = (
    "The declared structure: comma-separated terms, a JSON file with a 'terms' list (a model or "
    f"'narxwatch select --json' output), linear:NY,NX for a linear ARX model, or '{RIG}' for SPEC §2's "
    "8 terms of the 2-DOF rig that 'narxwatch simulate' models. Default: none; the loop starts from the "
    "linear model whose orders (up to 10) simulate best, and reports them."
)
VALIDATE_HELP = (
    "Records to judge both models on, each whole, without refitting: every file after --validate up "
    "to the next option (or --validate repeated)."
)


class DataFormat(StrEnum):
    auto = "auto"
    silverbox = "silverbox"


@dataclass(frozen=True)
class _Record:
    """A record as its file holds it: the file, the names of its signals there, the signals
    and the sampling rate."""

    path: Path
    layout: Layout
    x: np.ndarray
    y: np.ndarray
    fs: float | None

    @property
    def source(self) -> dict[str, Any]:
        """Where the record comes from, for the report."""
        return {"path": str(self.path), "x": self.layout.x, "y": self.layout.y}

    @property
    def name(self) -> str:
        """The record as messages name it: its file, and its signals where not the plain x and y."""
        return f"{self.path}{_signals(self.source)}"


@dataclass(frozen=True)
class PartOptions:
    """Which samples of the records are fitted, tested and scored, as given (each field an
    option; :func:`~simulator.client.groups.expanded`)."""

    estimation: Annotated[
        str | None,
        typer.Option(
            help="Estimation samples A:B of the one record (default: first 2/3; Silverbox: official); "
            "A:B,C:D,… fits the parts as records of their own, no lag crossing from one to the next, "
            "to leave out the samples between them (a glitch)."
        ),
    ] = None
    test: Annotated[
        str | None,
        typer.Option(
            help="Test samples C:D of the one record (default: the last third; Silverbox: the arrow)."
        ),
    ] = None
    transient: Annotated[
        int,
        typer.Option(
            help="Samples at the start of every record that hold its transient (e.g. the F-16 multisine's "
            "first period, 8192): records used whole are fitted through them and run from their start, "
            "and scored after them; on one record's parts, --estimation and --test count from there."
        ),
    ] = 0
    initial: Annotated[
        int | None,
        typer.Option(help="Measured samples each test free run starts from (Silverbox: 50)."),
    ] = None

    def on_one_record(self, fitted: list[_Record], held: list[_Record], silverbox: bool) -> bool:
        """Whether the loop runs on parts of one record: a single one, and no ``--validate`` or a
        part or benchmark split named; else on whole records."""
        named = self.estimation is not None or self.test is not None or silverbox
        return len(fitted) == 1 and (not held or named)


@dataclass(frozen=True)
class ReportOptions:
    """How the report is given, as given (each field an option)."""

    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False
    plot: Annotated[
        Path | None, typer.Option(help="Write a PNG of the residuals and the free run on the first test.")
    ] = None
    unit: Annotated[
        str | None,
        typer.Option(help="The output's unit, for the figures printed and plotted (Silverbox: V)."),
    ] = None


@expanded
def refine_command(
    *,
    data: Annotated[
        list[Path],
        typer.Argument(
            help="Estimation record(s): .csv or .npz as 'narxwatch simulate' writes, a CSV or MAT file "
            f"(--x, --y). {RECORD_SET_HELP}"
        ),
    ],
    declared: Annotated[str | None, typer.Option(help=DECLARED_HELP)] = None,
    data_format: Annotated[
        DataFormat,
        typer.Option("--format", help="'silverbox' for the benchmark's CSV files (--x V1 --y V2, its rate)."),
    ] = DataFormat.auto,
    x: XName = None,
    y: YName = None,
    fs: Annotated[float | None, typer.Option(help="Sampling rate [Hz] of files that state none.")] = None,
    samples: PartOptions,
    alpha: Annotated[float, typer.Option(help="Family-wise level of each round.")] = DEFAULT_ALPHA,
    validate: Annotated[list[Path] | None, typer.Option(help=VALIDATE_HELP)] = None,
    reporting: ReportOptions,
    jobs: Annotated[
        int | None,
        typer.Option(
            help="Processes that run the loop's independent pieces (candidates, judgements, searches), "
            "and threads that test the candidates, the report the same whatever their number "
            "(default: the CPUs this command may use)."
        ),
    ] = None,
) -> None:
    """Fit the declared model, trace its residual to the effects it lacks, add them, compare."""
    hold_freed_memory()
    silverbox = data_format is DataFormat.silverbox
    unit = reporting.unit or (SILVERBOX_UNIT if silverbox else None)
    layout = signal_layout(x, y, SILVERBOX if silverbox else DEFAULT_LAYOUT)
    transient = samples.transient
    if transient < 0:
        raise InputError(f"--transient must be 0 or more, got {transient}")
    jobs = _jobs(jobs)
    fitted = [record for path in data for record in _read(path, layout, fs, transient)]
    held = [record for path in validate or [] for record in _read(path, layout, fs, transient)]
    rate = common_rate([(record.name, record.fs) for record in (*fitted, *held)])
    start = samples.initial if samples.initial is not None else (SILVERBOX_INITIAL if silverbox else 0)
    loop = Loop(_declared(declared), start, alpha, rate, transient)
    if samples.on_one_record(fitted, held, silverbox):
        refined, judged, protocol = _on_parts(fitted[0], held, loop, jobs, samples, silverbox)
    else:
        refined, judged, protocol = _on_records(fitted, held, loop, jobs, samples)
    document = refined.to_dict(judged)
    document["data"] = protocol | {
        "transient": transient,
        "initial": start,
        "fs": rate,
        "alpha": alpha,
        "unit": unit,
    }
    if reporting.plot is not None:
        _write_figure(refined, loop, reporting.plot, layout.y, unit)
    if reporting.as_json:
        stdout.print_json(json.dumps(document))
        return
    _print(document, reporting.plot)


def _write_figure(refined: Refined, loop: Loop, plot: Path, output: str, unit: str | None) -> None:
    """The PNG ``--plot`` asks for, of the residuals and the free run on the record explained."""
    from service.cli.refine_figure import write_refinement_figure  # matplotlib only when asked

    report, explanation = refined.report, refined.explanation
    write_refinement_figure(
        report, *refined.explained, loop.initial, loop.fs, plot, output, unit, explanation
    )


def _on_parts(
    record: _Record,
    held: list[_Record],
    loop: Loop,
    jobs: int,
    given: PartOptions,
    silverbox: bool,
) -> tuple[Refined, list[dict[str, Any]], dict[str, Any]]:
    """The loop on parts of one record, counted after its transient: the refinement, where each
    record judged comes from, and the estimation parts, with samples as the files number them."""
    transient = loop.transient
    x_cut, y_cut = record.x[transient:], record.y[transient:]
    n = len(y_cut)
    defaults = (SILVERBOX_ESTIMATION, SILVERBOX_TEST) if silverbox else default_split(n)
    parts = _parts(given.estimation, n, defaults[0])
    c, d = _span(given.test, n, defaults[1], "--test")
    with _running(loop, jobs) as running:
        held_signals = [(r.x, r.y) for r in held]
        refined = refine_parts(
            running, x_cut, y_cut, parts, (c, d), held_signals, [r.path.name for r in held]
        )
    judged = [record.source | {"samples": [transient + c, transient + d]}]
    judged += [_whole(r, transient) for r in held]
    protocol = {"estimation": [record.source | {"samples": [transient + a, transient + b]} for a, b in parts]}
    return refined, judged, protocol


def _on_records(
    fitted: list[_Record],
    held: list[_Record],
    loop: Loop,
    jobs: int,
    given: PartOptions,
) -> tuple[Refined, list[dict[str, Any]], dict[str, Any]]:
    """The loop on whole records, each validation record judged: the refinement, where each
    record judged comes from, and the estimation records."""
    for option, value in (("--estimation", given.estimation), ("--test", given.test)):
        if value is not None:
            raise InputError(
                f"{option} picks a part of one record; with several estimation records (or --validate) "
                "each record is used whole (--transient: samples not scored)"
            )
    if not held:
        raise InputError("with several estimation records, name the records to judge on: --validate VAL…")
    # The loop fits whole records: a NARX model holds through the transient, and its check runs
    # then start where the records do, at rest. Started mid-record from L measured outputs
    # instead, F-16's multisines' check runs favoured least squares over output error, whose
    # slow mode carries those readings' noise (docs/benchmarks/measured.md, "Free runs started
    # mid-record").
    with _running(loop, jobs) as running:
        fitted_signals, held_signals = [(r.x, r.y) for r in fitted], [(r.x, r.y) for r in held]
        refined = refine_whole(running, fitted_signals, held_signals, [r.name for r in fitted])
    judged = [_whole(r, loop.transient) for r in held]
    return refined, judged, {"estimation": [_whole(r, 0) for r in fitted]}


def _jobs(jobs: int | None) -> int:
    """The processes ``--jobs`` asks for (default: the CPUs this command may use), refused beyond
    :data:`JOBS_PER_CPU` a CPU."""
    cpus = _usable_cpus()
    if jobs is not None and not 1 <= jobs <= JOBS_PER_CPU * cpus:
        raise InputError(
            f"--jobs must be 1 or more and at most {JOBS_PER_CPU * cpus}, twice the CPUs this command "
            f"may use; got {jobs}"
        )
    return jobs or cpus


def _read(path: Path, layout: Layout, fs: float | None, transient: int) -> list[_Record]:
    """The file's records (one, or one from each pair of groups x and y name), each longer than
    its transient."""
    records = []
    for pair, record in read_record_set(path, layout):
        if transient >= len(record.y):
            raise InputError(f"{path}: --transient {transient} leaves nothing of its {len(record.y)} samples")
        rate = record.fs if record.fs is not None else fs
        records.append(_Record(path, pair, record.x, record.y, rate))
    return records


def _whole(record: _Record, first: int) -> dict[str, Any]:
    """Where a record used whole comes from, and the samples fitted or scored: from ``first`` on."""
    return record.source | {"samples": [first, len(record.y)]}


@contextmanager
def _running(loop: Loop, jobs: int) -> Iterator[Loop]:
    """The loop as it runs here: its stages shown (:func:`_stages`), its independent pieces in
    ``jobs`` processes (:func:`_workers`)."""
    with _stages() as stage, _workers(jobs) as (workers, threads):
        yield replace(loop, progress=stage, workers=workers, threads=threads)


@contextmanager
def _stages() -> Iterator[Stage]:
    """The loop's stage as it runs, with a spinner and the time taken, on a terminal (nothing on
    a pipe or file); gone once the report is printed."""
    with transient_progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn()) as bar:
        task = bar.add_task("starting the loop", total=None)
        # Drawn at once: a stage shorter than the bar's refresh would otherwise not be seen at all.
        yield lambda stage: bar.update(task, description=stage, refresh=True)


@contextmanager
def _workers(jobs: int) -> Iterator[tuple[Workers, Workers]]:
    """The maps the loop runs its independent pieces with: in ``jobs`` processes, and in as many
    threads of this process for its own numpy work (``models.refinement.refine``); the builtin
    map for 1. However the command ends — done, Ctrl-C, terminated or killed — its workers end
    with it."""
    if jobs == 1:
        yield map, map
        return
    with (
        ProcessPoolExecutor(jobs, initializer=_worker_start, initargs=(os.getpid(),)) as pool,
        ThreadPoolExecutor(jobs) as threads,
    ):
        try:
            _start(pool)
            yield pool.map, threads.map
        except BaseException:
            pool.shutdown(cancel_futures=True)  # the families still queued are not built
            raise


def _start(pool: ProcessPoolExecutor) -> None:
    """Start the pool's workers, with Ctrl-C held off until each ignores it (:func:`_worker_start`).

    A pool that forks its workers does so at its first task, all of them, and then starts the
    thread that will tell them to stop. A Ctrl-C in between (the workers forked, that thread not
    started) left the command waiting for ever at its exit for workers nobody told to stop; and
    one that reached a worker still starting printed its traceback. Held off here, it reaches the
    command once the pool is whole, and the workers not at all."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        pool.submit(int).result()
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _worker_start(command: int) -> None:
    """A worker's start. A terminal's Ctrl-C reaches the workers too: the command stops them,
    rather than each printing its own traceback (a worker is forked with it held off, and the
    one that came meanwhile is dropped as it is unblocked). A worker whose command ended without
    stopping it (SIGTERM from ``timeout`` or a service manager, SIGKILL) ends with it
    (:func:`_end_with`), where it would wait for work for ever."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _end_with(command)


# prctl(2)'s option: the signal this process gets as the thread that forked it ends.
PR_SET_PDEATHSIG = 1


def _end_with(command: int) -> None:
    """End this worker as ``command``, the process that forked it, ends: on Linux the kernel
    kills it then (the pool forks its workers from the command's main thread, whose end is the
    command's); elsewhere a thread looks for its parent every second. A command that ended
    before the request was made is seen by the parent already being another."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        asked = libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (AttributeError, OSError):  # no prctl: not Linux
        asked = False
    if not asked:
        threading.Thread(target=_leave_when_orphaned, args=(command,), daemon=True).start()
    if os.getppid() != command:
        os._exit(1)


def _leave_when_orphaned(command: int) -> None:
    while os.getppid() == command:
        time.sleep(1.0)
    os._exit(1)


def _usable_cpus() -> int:
    """The CPUs this process may run on (its affinity where the system has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _declared(spec: str | None) -> tuple[Term, ...] | None:
    """The declared terms; None lets the loop choose a linear model's orders."""
    if spec is None:
        return None
    if spec.startswith("linear:"):
        orders = spec.removeprefix("linear:").split(",")
        try:
            ny, nx = (int(value) for value in orders)
        except ValueError:
            raise InputError(f"cannot read {spec!r}: write linear:NY,NX, e.g. linear:4,4") from None
        return linear_terms(ny, nx)
    return read_terms(spec)


def _parts(spec: str | None, n: int, default: tuple[int, int]) -> list[tuple[int, int]]:
    """The estimation parts ``--estimation`` names, A:B or A:B,C:D,… (the loop refuses parts that
    overlap)."""
    return [_span(each, n, default, "--estimation") for each in (spec.split(",") if spec else [None])]


def _span(spec: str | None, n: int, default: tuple[int, int], option: str) -> tuple[int, int]:
    if spec is None:
        first, last = default
    else:
        try:
            first, last = (int(value) for value in spec.split(":"))
        except ValueError:
            raise InputError(f"{option} {spec!r}: write A:B with sample numbers, e.g. 0:20000") from None
    if not 0 <= first < last <= n:
        raise InputError(f"{option} {first}:{last} does not lie within the record's {n} samples")
    return first, last


def _print(report: dict[str, Any], plot: Path | None) -> None:
    unit = report["data"]["unit"]
    per = f" {unit}" if unit else ""  # after a figure
    orders = report["orders_chosen"]
    if orders is not None:
        ny, nx, delay = orders
        stdout.print(
            f"nothing declared: the loop chose the linear model ny = {ny}, nx = {nx}, input delay {delay}",
            highlight=False,
        )
    stdout.print(f"declared: {', '.join(report['declared']['terms'])}", highlight=False, markup=False)
    _print_withdrawn(report)
    _print_explanation(report, per)
    _print_effects(report, per)
    _print_rounds(report["rounds"])
    if report["held_out"] is not None:
        _print_held_out(report["held_out"], per)
    stdout.print(f"refined parameters by {report['refined']['estimator']}")
    _print_range(report)
    _print_floor(report, per)
    _print_tests(report["tests"], unit)
    _print_notes(report)
    if plot is not None:
        stdout.print(f"figure -> {plot}")


def _print_withdrawn(report: dict[str, Any]) -> None:
    """The effects withdrawn and why, or that none was added."""
    held_out = report["held_out"]
    if held_out is not None and not held_out["refined_returned"]:
        why = (
            kinked_laws_reason(held_out["kinks_beyond"])
            if held_out.get("kinks_beyond")
            else "the refined model was not better than the start on the held-out tails"
        )
        stdout.print(
            f"withdrawn: {', '.join(report['effects_withdrawn'])} — {why} (below)",
            highlight=False,
            markup=False,
        )
    elif report["effects_withdrawn"]:
        stdout.print(
            f"withdrawn: {', '.join(report['effects_withdrawn'])} — with output-error parameters the "
            "declared model simulates the check blocks as well without them (from three records on: "
            "on one fold at least)",
            highlight=False,
            markup=False,
        )
    elif not report["effects_added"]:
        stdout.print("no effect lowers the error enough: nothing added")


def _print_effects(report: dict[str, Any], per: str) -> None:
    """Each effect added, in order, with its evidence, and its share and coefficients under it."""
    for number, effect in enumerate(report["effects_added"], start=1):
        evidence = effect["evidence"]
        before, after = (_number(value) for value in evidence["check_free_run_rms"])
        p_values = evidence["p_values"]
        stdout.print(
            f"{number}. {effect['name']} ({effect['description']}): {', '.join(effect['terms'])}"
            f" — decided by the {effect['decided_by']} criterion"
            f" (check blocks' free run {before} → {after}{per};"
            f" explains {evidence['explained_fraction']:.1%} of the residual"
            + (f", smallest p {_p(min(p_values))}, level {evidence['level']:.1e})" if p_values else ")"),
            highlight=False,
            markup=False,
        )
        _print_contribution(effect["contribution"], report["refined"]["saturation"], per)


def _print_rounds(rounds: list[dict[str, Any]]) -> None:
    """A line a round: the candidates it compared on the check blocks' free run, the fall of that
    free run it saw against the fall needed, what it added and what the pruning took out."""
    stdout.print("each round's choice (falls of the check blocks' free run):")
    for step in rounds:
        gain, needed = (f"{v:.1%}" if v is not None else "–" for v in (step["gain"], step["threshold"]))
        pruned = f"; pruned {', '.join(step['pruned'])}" if step["pruned"] else ""
        whole = " (pruned whole after the rounds)" if step["pruned_whole"] else ""
        aside = " (set aside on the held-out tails)" if step["set_aside"] else ""
        stdout.print(
            f"  {step['round']}: {step['candidates_tried']} tried, fall {gain} against {needed} needed"
            f" → {step['added'] or 'nothing added'}{whole}{aside}{pruned}",
            highlight=False,
            markup=False,
        )


def _print_floor(report: dict[str, Any], per: str) -> None:
    """The check blocks' free run beside the noise between periods that no model can simulate,
    where the records repeat their excitation."""
    floor = report["noise_floor"]
    check = report["check_free_run_rms"]
    if floor is None or check is None:
        return
    beneath = floor["check_model_error"]
    stdout.print(
        f"check blocks' free run {check:.4g}{per} RMS; the noise between the checked records' periods "
        f"({floor['periods']} of {floor['period']} samples), which no model can simulate, is "
        f"{floor['rms']:.4g} ± {floor['standard_error']:.2g}{per}: "
        + (
            f"about {beneath:.2g}{per} RMS of the check figure is the model's own error, all that any "
            "model could still take off"
            if beneath
            else "the check figure is at that floor, and no model can be told better on these records"
        ),
        highlight=False,
        markup=False,
    )


def _print_tests(tests: list[dict[str, Any]], unit: str | None) -> None:
    """Both models' one-step and free-run errors on each record judged, a row a record."""
    rms = f" [{unit}]" if unit else ""
    stdout.print(f"{'one-step RMS' + rms:^23} {'free-run RMS' + rms:^23}  Ljung–Box p", markup=False)
    stdout.print(f"{'before':>11} {'after':>11} {'before':>11} {'after':>11}  {'after':>11}  judged on")
    for item in tests:
        first, last = item["samples"]
        cells = [_number(item[label]["one_step_rms"]) for label in ("before", "after")] + [
            "diverged" if item[label]["diverged"] else _number(item[label]["free_run_rms"])
            for label in ("before", "after")
        ]
        stdout.print(
            " ".join(f"{cell:>11}" for cell in cells)
            + f"  {_p_cell(item['after'])}  {item['path']}{_signals(item)}"
            f" [{first}:{last}]",
            highlight=False,
            markup=False,
        )


def _print_range(report: dict[str, Any]) -> None:
    """Both models' amplitude ranges: up to what scale of the estimation inputs each one's free
    run stays bounded (:mod:`models.amplitude_range`)."""
    ranges = report["amplitude_range"]
    start = "linear start" if report["orders_chosen"] is not None else "declared model"
    scales = ", ".join(f"{scale:g}" for scale in ranges["scales"])
    stdout.print(
        f"amplitude range (free runs over the estimation inputs scaled by {scales}): the {start} "
        f"{ranges['declared']['description']}; the refined model {ranges['refined']['description']}",
        highlight=False,
        markup=False,
    )


def _print_notes(report: dict[str, Any]) -> None:
    """The records on which the refined model diverged (and why, where they reach beyond its
    amplitude range) or that lie partly outside the estimation data, then the report's notes."""
    for item in report["tests"]:
        if item["verdict"] == "diverged":
            why = item["beyond_amplitude_range"]
            stdout.print(
                f"note: on {item['path']}{_signals(item)} the refined model's free run diverged"
                + (f": {why}" if why else ""),
                highlight=False,
                markup=False,
            )
    for item in report["tests"]:
        if item["coverage"]["extrapolates"]:
            stdout.print(
                f"note: {item['path']}{_signals(item)} lies partly outside the estimation data "
                f"({item['coverage']['description']}): its figures judge the models where they extrapolate",
                highlight=False,
                markup=False,
            )
    for note in report["notes"]:
        stdout.print(f"note: {note}", highlight=False, markup=False)


def _print_held_out(held_out: dict[str, Any], per: str) -> None:
    """The comparison of the refined model with the start on the held-out tails, and its decision."""
    start, refined = (_number(held_out[key]) for key in ("start_free_run_rms", "refined_free_run_rms"))
    gain = (
        "the refined model diverged"
        if held_out["diverged"]
        else f"gain {_share(held_out['gain'])} of the mean square, threshold {_share(held_out['threshold'])} "
        f"(its uncertainty at level {held_out['level']:g})"
    )
    # Reports stored before the gate named kinked laws carry no such list.
    kinks = held_out.get("kinks_beyond")
    decision = (
        "the refined model is returned"
        if held_out["refined_returned"]
        else f"the start is returned (the best effect tried: {held_out['best_tried']})"
        + (f": {kinked_laws_reason(kinks)}" if kinks else "")
    )
    stdout.print(
        f"held-out tails ({held_out['samples']} samples {unseen_by(held_out['orders_saw_tails'])}): "
        f"free-run RMS start {start}{per}, "
        f"refined {refined}{per}; {gain}: {decision}",
        highlight=False,
        markup=False,
    )


def _print_explanation(report: dict[str, Any], per: str) -> None:
    """What the effects' shares printed under each are (:mod:`models.explanation`), and the
    declared part's, where effects were added."""
    if not report["effects_added"]:
        return
    explanation, judged = report["explanation"], report["tests"][0]
    first, last = judged["samples"]
    part = "the linear start" if report["orders_chosen"] is not None else "the declared part"
    stdout.print(
        f"under each effect, shares of the output's RMS ({explanation['output_rms']:.4g}{per}) on "
        f"{judged['path']}{_signals(judged)} [{first}:{last}]: of each step, its terms times their "
        f"coefficients along the refined model's {explanation['along']} ({part}: "
        f"{_percent(explanation['declared']['share'])}); and how far the free run moves without it",
        highlight=False,
        markup=False,
    )


def _share(value: float | None) -> str:
    return f"{value:.1%}" if value is not None else "—"


def _print_contribution(contribution: dict[str, Any], saturation: str | None, per: str) -> None:
    """An effect's share and coefficients (± their standard errors), under its line."""
    errors = contribution["standard_errors"] or [None] * len(contribution["terms"])
    coefficients = ", ".join(
        f"{term} = {value:.4g}" + (f" ± {error:.2g}" if error is not None else "")
        for term, value, error in zip(
            contribution["terms"], contribution["coefficients"], errors, strict=True
        )
    )
    without = (
        "the free run diverges without it"
        if contribution["diverges_without"]
        else f"without it the free run moves {_percent(contribution['removal_share'])}"
    )
    if "limits" in contribution:
        low, high = (f"{value:.4g}" if value is not None else "none" for value in contribution["limits"])
        at = contribution["at_limits"]
        line = f"the {saturation} saturates at {low} and {high}{per}" + (
            f", the free run at a limit in {_percent(at)} of its samples" if at is not None else ""
        )
        line += f"; {without}"
    elif contribution["share"] is None:
        line = f"the one-step prediction's, not in the free run: {coefficients}"
    else:
        line = f"of each step {_percent(contribution['share'])}; {without}: {coefficients}"
    stdout.print(f"   {line}", highlight=False, markup=False)


def _percent(value: float | None) -> str:
    """A share to three significant figures: an effect's share of each step can be a millionth."""
    return f"{100 * value:.3g} %" if value is not None else "none"


def _signals(source: dict[str, Any]) -> str:
    """The signals a record was read from, where they are not the plain x and y."""
    return "" if (source["x"], source["y"]) == ("x", "y") else f" ({source['x']}, {source['y']})"


def _p_cell(assessment: dict[str, Any]) -> str:
    """The Ljung–Box p-value's cell: "skipped" on a test part too short for the test."""
    if assessment["skipped_tests"]:
        return f"{'skipped':>11}"
    return f"{assessment['ljung_box_p'] or 0:>11.3g}"


def _number(value: float | None) -> str:
    return f"{value:.4g}" if value is not None else "diverged"


def _p(value: float) -> str:
    return f"{value:.1e}" if value > 0 else "< 1e-300"  # below the smallest double, not zero
