"""``narxwatch train``: estimate a baseline NARX or a fault-mode FNARX model."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from models.baseline_choice import choose_baseline_terms
from models.basis import FAMILIES
from models.fnarx import fit_fnarx
from models.narx import fit_narx
from recordfiles.names import normalised_name
from service.cli.console import stdout
from service.cli.modelfiles import (
    RECORD_SET_HELP,
    RIG,
    XName,
    YName,
    read_manifest,
    read_record_sets,
    read_records,
    read_terms,
    signal_layout,
    write_json,
)

app = typer.Typer(help="Estimate models from records.", no_args_is_help=True)

TERMS_HELP = (
    "Model structure: comma-separated term names (e.g. 'y[t-1],y[t-2]^3,x[t-4]'), a JSON file with a "
    f"'terms' list (a baseline's model file, `narxwatch select --json`), or '{RIG}' for the paper rig's "
    "8 terms (SPEC §2)."
)
FAULT_MODE_TERMS_HELP = (
    TERMS_HELP + " A fault mode extends its baseline: --terms baseline.json takes its terms."
)
BASELINE_TERMS_HELP = (
    TERMS_HELP + " Default: chosen for the structure from these records (the linear orders and input "
    "delay that simulate held-out parts of them best, then nonlinear terms where they lower that)."
)


@app.command("baseline")
def baseline(
    records: Annotated[
        list[Path], typer.Argument(help=f"Healthy records (.csv, .npz or .mat). {RECORD_SET_HELP}")
    ],
    out: Annotated[Path, typer.Option("--out", help="Model file to write (.json).")],
    terms: Annotated[str | None, typer.Option(help=BASELINE_TERMS_HELP)] = None,
    x: XName = None,
    y: YName = None,
) -> None:
    """Identify the healthy structure as a NARX model from one or more records."""
    loaded, fs = read_records(records, signal_layout(x, y))
    signals = [(r.x, r.y) for r in loaded]
    choice = None if terms is not None else choose_baseline_terms(signals)
    model = fit_narx(signals, read_terms(terms) if choice is None else choice.terms)
    document = model.to_document()
    document["metadata"] = {"fs": fs, "records": [str(p) for p in records]}
    if choice is not None:
        document["metadata"]["choice"] = choice.to_dict()
        stdout.print(
            f"terms chosen: ARX({choice.ny}, {choice.nx}), input delay {choice.delay}, "
            f"{', '.join(t.name for t in choice.added) or 'no nonlinear term'} added; free-run NRMSE over "
            f"held-out parts of the records {choice.held_out_nrmse:.2%}",
            markup=False,
            highlight=False,
        )
    write_json(out, document)
    stdout.print(f"baseline NARX with {len(model.terms)} terms from {model.n_obs} equations -> {out}")
    for name, value, (low, high) in zip(model.term_names, model.theta, model.intervals(), strict=True):
        stdout.print(f"  {name:>12}  {value: .6e}  [{low: .6e}, {high: .6e}]", markup=False, highlight=False)


@app.command("fault-mode")
def fault_mode(
    name: Annotated[str, typer.Option(help="Fault-mode name, e.g. k2.")],
    experiments: Annotated[
        Path,
        typer.Option(
            help="Manifest CSV with columns path,k: each file's records (--x and --y naming groups of as "
            "many signals: one a pair) are experiments at its k."
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Model file to write (.json).")],
    terms: Annotated[str, typer.Option(help=FAULT_MODE_TERMS_HELP)],
    basis: Annotated[str, typer.Option(help=f"Functional basis: {', '.join(FAMILIES)}.")] = "chebyshev2",
    degree: Annotated[int, typer.Option(help="Degree of the basis (p = degree + 1 functions).")] = 1,
    k_min: Annotated[
        float | None, typer.Option(help="Lower end of the fault range (default: smallest k).")
    ] = None,
    k_max: Annotated[
        float | None, typer.Option(help="Upper end of the fault range (default: largest k).")
    ] = None,
    x: XName = None,
    y: YName = None,
) -> None:
    """Identify a fault mode as a functional NARX model from experiments at several magnitudes."""
    rows = read_manifest(experiments)
    # A file of several realisations (x and y naming groups) gives that many experiments at its k.
    sets, fs = read_record_sets([path for path, _ in rows], signal_layout(x, y))
    ks = [k for _, k in rows]
    k_range = (min(ks) if k_min is None else k_min, max(ks) if k_max is None else k_max)
    model = fit_fnarx(
        [(r.x, r.y, k) for found, k in zip(sets, ks, strict=True) for r in found],
        read_terms(terms),
        name=normalised_name(name, "fault-mode name"),
        family=basis,  # type: ignore[arg-type]  # checked by FunctionalBasis
        size=degree + 1,
        k_range=k_range,
    )
    document = model.to_document()
    document["metadata"] = {"fs": fs, "experiments": [{"path": str(p), "k": k} for p, k in rows]}
    write_json(out, document)
    stdout.print(
        f"fault-mode model {name!r}: {len(model.terms)} terms × {model.basis.size} {basis} functions "
        f"on k ∈ [{k_range[0]:g}, {k_range[1]:g}] from {len(rows)} experiments -> {out}"
    )
