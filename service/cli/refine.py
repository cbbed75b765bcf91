"""``narxwatch refine``: find the effects a declared model lacks and report the error before and after."""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from models.assessment import assess, assessment_dict
from models.effects import linear_terms
from models.errors import InputError
from models.refinement import DEFAULT_ALPHA, refine_record
from models.terms import Term
from service.cli.console import stdout
from service.cli.modelfiles import XName, YName, read_terms, signal_layout
from service.recordfiles import DEFAULT_LAYOUT, SILVERBOX, read_record

# The Silverbox benchmark's official split (shared/data/README.md): estimation and arrow test,
# each test run started from 50 measured outputs.
SILVERBOX_ESTIMATION = (40650, 105712)
SILVERBOX_TEST = (100, 40575)
SILVERBOX_INITIAL = 50

DECLARED_HELP = (
    "The declared structure: comma-separated terms, a JSON file with a 'terms' list (a model or "
    "'narxwatch select --json' output), or linear:NY,NX for a linear ARX model. Default: SPEC §2's "
    "8 terms of the 2-DOF structure."
)


class DataFormat(StrEnum):
    auto = "auto"
    silverbox = "silverbox"


def refine_command(
    data: Annotated[
        Path,
        typer.Argument(
            help="Record: .csv or .npz as 'narxwatch simulate' writes, a CSV or MAT file (--x, --y)."
        ),
    ],
    declared: Annotated[str | None, typer.Option(help=DECLARED_HELP)] = None,
    data_format: Annotated[
        DataFormat,
        typer.Option("--format", help="'silverbox' for the benchmark's CSV files (--x V1 --y V2, its rate)."),
    ] = DataFormat.auto,
    x: XName = None,
    y: YName = None,
    fs: Annotated[float | None, typer.Option(help="Sampling rate [Hz] if the file has none.")] = None,
    estimation: Annotated[
        str | None,
        typer.Option(help="Estimation samples A:B (default: first 2/3; Silverbox: official)."),
    ] = None,
    test: Annotated[
        str | None, typer.Option(help="Test samples C:D (default: the last third; Silverbox: the arrow).")
    ] = None,
    initial: Annotated[
        int | None, typer.Option(help="Test samples that only start the predictions (Silverbox: 50).")
    ] = None,
    alpha: Annotated[float, typer.Option(help="Family-wise level of each round.")] = DEFAULT_ALPHA,
    validate: Annotated[
        list[Path] | None,
        typer.Option(help="Further records (same format) to judge both models on, whole, without refitting."),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the report as JSON.")] = False,
    plot: Annotated[Path | None, typer.Option(help="Write a PNG of the residuals and the free run.")] = None,
) -> None:
    """Fit the declared model, trace its residual to the effects it lacks, add them, compare."""
    layout = signal_layout(x, y, SILVERBOX if data_format is DataFormat.silverbox else DEFAULT_LAYOUT)
    record = read_record(data, layout)
    rate = record.fs if record.fs is not None else fs
    silverbox = data_format is DataFormat.silverbox
    n = len(record.x)
    est = _span(estimation, n, SILVERBOX_ESTIMATION if silverbox else (0, 2 * n // 3), "--estimation")
    held = _span(test, n, SILVERBOX_TEST if silverbox else (2 * n // 3, n), "--test")
    start = initial if initial is not None else (SILVERBOX_INITIAL if silverbox else 0)
    report = refine_record(record.x, record.y, _declared(declared), est, held, start, alpha, rate)
    document = report.to_dict() | {
        "data": {"estimation": list(est), "test": list(held), "initial": start, "fs": rate, "alpha": alpha}
    }
    document["validation"] = [
        {
            "path": str(path),
            "before": assessment_dict(assess(report.refinement.declared, other.x, other.y, start, other.fs)),
            "after": assessment_dict(
                assess(
                    report.refinement.refined,
                    other.x,
                    other.y,
                    start,
                    other.fs,
                    noise=report.refinement.noise,
                )
            ),
        }
        for path, other in ((path, read_record(path, layout)) for path in validate or [])
    ]
    if plot is not None:
        from service.cli.refine_figure import write_refinement_figure  # matplotlib only when asked

        c, d = held
        write_refinement_figure(report, record.x[c:d], record.y[c:d], start, rate, plot)
    if as_json:
        stdout.print_json(json.dumps(document))
        return
    _print(document, plot)


def _declared(spec: str | None) -> tuple[Term, ...]:
    if spec is not None and spec.startswith("linear:"):
        orders = spec.removeprefix("linear:").split(",")
        try:
            ny, nx = (int(value) for value in orders)
        except ValueError:
            raise InputError(f"cannot read {spec!r}: write linear:NY,NX, e.g. linear:4,4") from None
        return linear_terms(ny, nx)
    return read_terms(spec)


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
    stdout.print(f"declared: {', '.join(report['declared']['terms'])}", highlight=False, markup=False)
    if not report["effects_added"]:
        stdout.print("no effect explains a significant part of the residual: nothing added")
    for number, effect in enumerate(report["effects_added"], start=1):
        evidence = effect["evidence"]
        stdout.print(
            f"{number}. {effect['name']} ({effect['description']}): {', '.join(effect['terms'])}"
            f" — explains {evidence['explained_fraction']:.1%} of the residual"
            f" (smallest p {_p(min(evidence['p_values']))}, level {evidence['level']:.1e})",
            highlight=False,
            markup=False,
        )
    stdout.print("on the test part:")
    _print_errors(report)
    for item in report["validation"]:
        stdout.print(f"validation on {item['path']} (no refitting):", highlight=False, markup=False)
        _print_errors(item)
    if plot is not None:
        stdout.print(f"figure -> {plot}")


def _print_errors(figures: dict[str, Any]) -> None:
    """The before/after table of one assessment; the Ljung–Box p-value may be 0 when far from white."""
    stdout.print(
        f"{'':>14} {'one-step RMS':>14} {'free-run RMS':>14} {'Ljung–Box p':>12}  residual tests failed"
    )
    for label in ("before", "after"):
        row = figures[label]
        cells = [
            f"{row[key]:.4g}" if row[key] is not None else "diverged"
            for key in ("one_step_rms", "free_run_rms", "ljung_box_p")
        ]
        failed = ", ".join(row["diagnostics"]["failed"]) or "none"
        stdout.print(
            f"{label:>14} {cells[0]:>14} {cells[1]:>14} {cells[2]:>12}  {failed}",
            highlight=False,
            markup=False,
        )


def _p(value: float) -> str:
    return f"{value:.1e}" if value > 0 else "< 1e-300"  # below the smallest double, not zero
