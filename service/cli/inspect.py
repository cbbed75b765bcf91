"""``narxwatch inspect``: run the inspection chain on one record."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from models.errors import InputError
from models.inspection import Verdict
from models.inspection import inspect as run_inspection
from recordfiles.reader import read_record
from service.cli.console import stdout
from service.cli.modelfiles import XName, YName, read_fault_mode, signal_layout

STATUS_STYLE = {"healthy": "green", "faulty": "red", "unknown_fault": "magenta", "anomaly": "magenta"}


def inspect(
    record: Annotated[Path, typer.Argument(help="Record to inspect (.csv, .npz or .mat).")],
    fault_mode: Annotated[list[Path], typer.Option(help="Fault-mode model file (repeatable).")],
    alpha: Annotated[float, typer.Option(help="Risk level of every test.")] = 0.05,
    lags: Annotated[int, typer.Option(help="Ljung–Box lags h.")] = 40,
    as_json: Annotated[bool, typer.Option("--json", help="Print the verdict as JSON.")] = False,
    x: XName = None,
    y: YName = None,
) -> None:
    """Detect, localise and size a fault: k̂ per mode, detection, Ljung–Box, interval (SPEC §5)."""
    data = read_record(record, signal_layout(x, y))
    models = []
    for path in fault_mode:
        model, fs = read_fault_mode(path)
        if fs is not None and data.fs is not None and fs != data.fs:
            raise InputError(
                f"{record} is sampled at {data.fs:g} Hz but {path} was trained at {fs:g} Hz; "
                "a NARX model holds at one sampling rate only"
            )
        models.append(model)
    verdict = run_inspection(data.x, data.y, models, alpha=alpha, lags=lags)
    if as_json:
        print(json.dumps(verdict.to_dict(), indent=1))
    else:
        _print_verdict(verdict)


def _print_verdict(verdict: Verdict) -> None:
    style = STATUS_STYLE[verdict.status]
    headline = f"[bold {style}]{verdict.status}[/]"
    if verdict.fault_mode:
        headline += f" — mode {verdict.fault_mode}"
    if verdict.interval:
        headline += (
            f", k̂ = {verdict.k_hat:.3f} % ± {verdict.sigma_k:.3f}, "
            f"{100 * (1 - verdict.alpha):g} % interval [{verdict.interval[0]:.3f}, {verdict.interval[1]:.3f}]"
        )
    stdout.print(headline)
    table = Table("mode", "k̂ [%]", "σ̂_k", "|k̂|/σ̂_k", "Q", "Q crit", "p", "accepted")
    for mode in verdict.modes:
        table.add_row(
            mode.name,
            f"{mode.k_hat:.4f}",
            f"{mode.sigma_k:.4f}",
            f"{abs(mode.z):.2f}" + (" *" if mode.detects else ""),
            f"{mode.q:.1f}",
            f"{mode.q_critical:.1f}",
            f"{mode.p_value:.3g}",
            "yes" if mode.accepted else "no",
        )
    stdout.print(table)
    stdout.print(
        f"{verdict.n_samples} samples, α = {verdict.alpha}, h = {verdict.lags}, "
        f"detection threshold |k̂|/σ̂_k > {verdict.z_critical:.3f} (* = detects)"
    )
