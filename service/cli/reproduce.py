"""``narxwatch reproduce``: the paper's study, its table side by side and its figures."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from service.cli.console import stdout
from simulator.paper import StudyResult, run_study
from simulator.study import CASES, PAPER_RESULTS, StudySettings


def reproduce(
    out: Annotated[Path, typer.Option("--out", help="Directory for results.json and the figures.")],
    runs: Annotated[int, typer.Option(help="Monte Carlo runs per test case.", min=1)] = 10,
    seed: Annotated[int, typer.Option(help="Seed of the whole study.")] = StudySettings.seed,
    monte_carlo: Annotated[
        int,
        typer.Option(
            help="Healthy and faulty records for the false-alarm and coverage checks (0: skip).", min=0
        ),
    ] = 500,
) -> None:
    """Run the paper's study (SPEC §6): a-priori phase, the four test cases, and beyond-paper checks."""
    settings = StudySettings(runs=runs, seed=seed)
    totals = {
        "experiments k2": len(settings.experiment_k),
        "experiments k1": len(settings.experiment_k),
        **{f"case {case.name}": runs for case in CASES},
        "noise levels": len(settings.noise_levels),
    }
    if monte_carlo:
        totals["Monte Carlo"] = monte_carlo
    with Progress(
        TextColumn("{task.description:>16}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stdout,
        transient=False,
    ) as bar:
        tasks = {name: bar.add_task(name, total=total) for name, total in totals.items()}
        result = run_study(settings, lambda name, step: bar.advance(tasks[name], step), monte_carlo)
    # matplotlib is loaded only here: it would add half a second to every other command.
    from service.cli.figures import write_figures

    out.mkdir(parents=True, exist_ok=True)
    document = result.to_dict()
    (out / "results.json").write_text(json.dumps(document, indent=1) + "\n")
    figures = write_figures(result, out)
    _print_table(result)
    stdout.print(f"results: {out / 'results.json'}; figures: {', '.join(p.name for p in figures)}")


def _print_table(result: StudyResult) -> None:
    table = Table(title="SPEC §6 — this run (paper)", title_justify="left")
    for column in ("case", "true k", "mean k̂", "mean σ̂_k", "detected", "k2 Q accepts", "localised"):
        table.add_column(column, justify="right")
    summaries = result.to_dict()["cases"]
    for case in CASES:
        ours, paper = summaries[case.name], PAPER_RESULTS[case.name]

        def pair(value: float | None, reference: float | None, fmt: str) -> str:
            mine = "—" if value is None else format(value, fmt)
            theirs = "—" if reference is None else format(reference, fmt)
            return f"{mine} ({theirs})"

        table.add_row(
            case.name,
            f"{case.true_k:g}",
            pair(ours["mean_k_hat"], paper["mean_k_hat"], ".4g"),
            pair(ours["mean_sigma_k"], paper["mean_sigma_k"], ".3g"),
            f"{ours['detected']}/{ours['runs']} ({paper['detected']}/10)",
            f"{ours['accepted_k2']}/{ours['runs']} ({paper['accepted_k2']}/10)",
            "—" if case.fault == "none" else f"{ours['localised']}/{ours['runs']} to {case.fault}",
        )
    stdout.print(table)
    iv = summaries["IV"]
    stdout.print(
        f"case IV against the k2 model alone: detected {iv['detected_by_k2_alone']}/{iv['runs']} "
        f"(paper 10/10), by its magnitude test alone {iv['k2_alone_magnitude_test_detects']}/{iv['runs']}; "
        f"with both models the k1 intervals contain 30 in {iv['interval_contains_true_k']}/{iv['runs']}"
    )
    noise = Table(
        "disturbance std [N]",
        "detected",
        "by the k̂ test",
        "mean k̂",
        "mean σ̂_k",
        "mean Q",
        title="case IV against the k2 model alone, by noise level",
        title_justify="left",
    )
    for row in result.noise_dependence:
        noise.add_row(
            f"{row['disturbance_std']:g}",
            f"{row['detected']}/{row['runs']}",
            f"{row['magnitude_test_detects']}/{row['runs']}",
            f"{row['mean_k_hat']:.3f}",
            f"{row['mean_sigma_k']:.3f}",
            f"{row['mean_q']:.0f}",
        )
    stdout.print(noise)
    if result.monte_carlo:
        mc = result.monte_carlo
        stdout.print(
            f"Monte Carlo, {mc['records']} healthy + {mc['records']} faulty records: false alarms "
            f"{mc['false_alarms']} (binomial 95 % bound at α: {mc['false_alarm_binomial_95_bound']}); "
            f"coverage {mc['coverage_with_model_term']:.3f} with the model term, "
            f"{mc['coverage_paper_sigma']:.3f} with the paper's σ̂_k "
            f"(|k| > 24: {mc['coverage_near_range_ends_with_model_term']:.3f} / "
            f"{mc['coverage_near_range_ends_paper_sigma']:.3f})"
        )
