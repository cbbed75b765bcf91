"""``narxwatch simulate``: write a simulated record of the 2-DOF structure."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from service.cli.console import parse_assignments, stdout
from simulator.physics import FAULT_MODES, PhysicalParameters
from simulator.recordfile import write_record
from simulator.simulate import EFFECTS, Effects, Scenario
from simulator.simulate import simulate as run_simulation

EFFECT_HELP = "Undeclared effect NAME=SIZE (repeatable): " + "; ".join(
    f"{name} [{unit}] {meaning}" for name, (unit, meaning) in EFFECTS.items()
)


def simulate(
    out: Annotated[Path, typer.Option("--out", help="Output file, .csv or .npz.")],
    fault: Annotated[str, typer.Option(help=f"Fault mode: {', '.join(FAULT_MODES)}.")] = "none",
    k: Annotated[
        float, typer.Option(help="Fault magnitude in percent (positive = stiffness reduction).")
    ] = 0.0,
    n: Annotated[int, typer.Option(help="Number of samples.")] = 2000,
    seed: Annotated[int | None, typer.Option(help="Random seed (default: fresh entropy).")] = None,
    excitation_std: Annotated[float, typer.Option(help="Std of the white force excitation x [N].")] = 25e3,
    disturbance_std: Annotated[
        float, typer.Option(help="Std of the unmeasured white force on mass 1 [N] (white NARX residual).")
    ] = 800.0,
    noise_std: Annotated[float, typer.Option(help="Std of white measurement noise on y [m].")] = 0.0,
    x_noise_std: Annotated[float, typer.Option(help="Std of white measurement noise on x [N].")] = 0.0,
    effect: Annotated[list[str] | None, typer.Option(help=EFFECT_HELP)] = None,
    param: Annotated[
        list[str] | None,
        typer.Option(
            help=f"Physical parameter NAME=VALUE (repeatable): {', '.join(PhysicalParameters.names())}."
        ),
    ] = None,
) -> None:
    """Simulate excitation x [N] and response y [m] of the 2-DOF structure (SPEC §1)."""
    params = PhysicalParameters().replace(**parse_assignments(param or [], "parameter"))
    scenario = Scenario(
        params=params,
        fault=fault,  # type: ignore[arg-type]  # checked by with_fault
        k=k,
        excitation_std=excitation_std,
        disturbance_std=disturbance_std,
        y_noise_std=noise_std,
        x_noise_std=x_noise_std,
        effects=Effects.parse(effect or []),
    )
    record = run_simulation(scenario, n, seed)
    path = write_record(out, record.x, record.y, record.fs)
    stdout.print(
        f"wrote {path}: {n} samples at fs = {record.fs:g} Hz, fault {fault} k = {k:g} %, "
        f"std(y) = {record.y.std():.4g} m"
    )
