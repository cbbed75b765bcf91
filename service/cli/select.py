"""``narxwatch select``: find a NARX structure from records by FROLS (SPEC §3)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from models.candidates import candidate_terms
from models.errors import InputError
from models.selection import CRITERIA, NarxSelection, select_narx
from models.validation import Validation, validate
from service.cli.console import stderr, stdout
from service.cli.modelfiles import XName, YName, read_records, signal_layout, write_json

Signals = list[tuple[np.ndarray, np.ndarray]]


def select(
    records: Annotated[list[Path], typer.Argument(help="Records to select from (.csv, .npz or .mat).")],
    x: XName = None,
    y: YName = None,
    degree: Annotated[int, typer.Option(help="Largest total degree of the candidate monomials.")] = 3,
    ny: Annotated[int, typer.Option(help="Output lags y[t-1] … y[t-ny].")] = 4,
    nx: Annotated[int, typer.Option(help="Input lags x[t-delay] … x[t-delay-nx+1].")] = 4,
    delay: Annotated[int, typer.Option(help="Input delay d: the smallest lag of x (0 allows x[t]).")] = 1,
    constant: Annotated[bool, typer.Option(help="Include the constant term 1.")] = True,
    extra: Annotated[
        list[str] | None, typer.Option(help="Extra candidate term beyond the dictionary (repeatable).")
    ] = None,
    include: Annotated[
        list[str] | None, typer.Option(help="Candidate taken first and always kept (repeatable).")
    ] = None,
    criterion: Annotated[
        str | None,
        typer.Option(
            help=f"Information criterion minimised along the path: {', '.join(CRITERIA)} "
            "(default bic, unless --n-terms or --err-tolerance is given)."
        ),
    ] = None,
    n_terms: Annotated[int | None, typer.Option(help="Select exactly this many terms.")] = None,
    err_tolerance: Annotated[
        float | None, typer.Option(help="Stop once the unexplained share 1 − ΣERR falls below this.")
    ] = None,
    max_terms: Annotated[int, typer.Option(help="Longest greedy path.")] = 20,
    prune: Annotated[
        bool, typer.Option(help="Then drop terms one at a time while the stopping rule still holds.")
    ] = False,
    precise: Annotated[
        bool,
        typer.Option(
            help="Explicitly orthogonalised path, exact to rounding level (noise-free data); slower."
        ),
    ] = False,
    holdout: Annotated[
        list[Path] | None, typer.Option(help="Held-out record for the validation errors (repeatable).")
    ] = None,
    split: Annotated[
        float,
        typer.Option(help="Without --holdout: share of each record's end held out for validation (0: none)."),
    ] = 0.25,
    steps: Annotated[int, typer.Option(help="Horizon k of the k-step prediction errors.")] = 10,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Write the result to this .json file (a file `train --terms` reads)."),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the result as JSON.")] = False,
) -> None:
    """Select NARX terms from a dictionary of lagged monomials by FROLS with the error reduction ratio.

    Prints the chosen terms with their ERR and least-squares parameters, and one-step, k-step
    and free-run errors on held-out data. The JSON (--json or --out) is accepted by
    `narxwatch train baseline --terms FILE`.
    """
    if out is not None and out.suffix.lower() != ".json":
        raise InputError(f"--out {out}: name a .json file, the kind `train --terms` reads")
    layout = signal_layout(x, y)
    loaded, fs = read_records(records, layout)
    signals = [(r.x, r.y) for r in loaded]
    if holdout:
        held, held_fs = read_records(holdout, layout)
        if None not in (fs, held_fs) and held_fs != fs:
            raise InputError(f"the held-out records are sampled at {held_fs:g} Hz, the others at {fs:g} Hz")
        validation_signals = [(r.x, r.y) for r in held]
    else:
        signals, validation_signals = _split(signals, split)
    candidates = candidate_terms(degree, ny, nx, delay, constant=constant, extra=extra or ())
    with Progress(
        TextColumn("selecting"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stderr,
        transient=True,
        disable=not stderr.is_terminal,
    ) as bar:
        task = bar.add_task("select", total=n_terms or min(max_terms, len(candidates)))
        selection = select_narx(
            signals,
            candidates,
            n_terms=n_terms,
            criterion=criterion,
            err_tolerance=err_tolerance,
            max_terms=max_terms,
            prune=prune,
            include=include or (),
            precise=precise,
            progress=lambda step: bar.update(task, completed=step),
        )
    held_out = validate(selection.model, validation_signals, steps) if validation_signals else None
    document = {
        **selection.to_dict(),
        "held_out": None if held_out is None else held_out.to_dict(),
        "dictionary": {
            "degree": degree,
            "ny": ny,
            "nx": nx,
            "delay": delay,
            "constant": constant,
            "extra": extra or [],
        },
        "records": [str(path) for path in records],
        "holdout": {"records": [str(path) for path in holdout or []], "split": None if holdout else split},
        "fs": fs,
    }
    if out is not None:
        write_json(out, document)
    if as_json:
        print(json.dumps(document, indent=1))
    else:
        _print_selection(selection, held_out)
        if out is not None:
            stdout.print(f"written to {out}")


def _split(signals: Signals, share: float) -> tuple[Signals, Signals]:
    """Each record's first (1 − share) for selection, its last ``share`` for validation."""
    if not 0 <= share < 1:
        raise InputError(f"--split must lie in [0, 1), got {share}")
    if share == 0:
        return signals, []
    fitting, held = [], []
    for x, y in signals:
        cut = len(y) - round(share * len(y))
        fitting.append((x[:cut], y[:cut]))
        held.append((x[cut:], y[cut:]))
    return fitting, held


def _print_selection(selection: NarxSelection, held_out: Validation | None) -> None:
    model = selection.model
    table = Table(
        "term",
        "ERR",
        "θ",
        "s.e.",
        title=f"{len(model.terms)} of {len(selection.candidates)} candidates",
        title_justify="left",
    )
    for name, err, theta, se in zip(
        model.term_names, selection.err, model.theta, model.standard_errors(), strict=True
    ):
        table.add_row(Text(name), f"{err:.4e}", f"{theta: .6e}", f"{se:.2e}")  # names hold [t-1]
    stdout.print(table)
    rule = selection.stopped_by
    stdout.print(
        f"stopped by {rule}; 1 − ΣERR = {selection.esr:.3e} on {model.n_obs} equations"
        + (
            f"; removed by pruning: {', '.join(t.name for t in selection.removed)}"
            if selection.removed
            else ""
        ),
        markup=False,
        highlight=False,
    )
    if held_out is not None:
        errors = Table("held out", "RMS", "NRMSE", "samples")
        for label, mode in (
            ("one-step", held_out.one_step),
            (f"{held_out.steps}-step", held_out.k_step),
            ("free run", held_out.free_run),
        ):
            errors.add_row(label, f"{mode.rms:.4e}", f"{mode.nrmse:.4e}", str(mode.samples))
        stdout.print(errors)
