"""``narxwatch simulate``: write a simulated record of the 2-DOF structure."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from recordfiles.writer import write_record
from service.cli.console import stdout
from simulator.options import (
    DisturbanceStd,
    EffectList,
    ExcitationStd,
    Fault,
    Magnitude,
    NoiseColour,
    NoiseStd,
    ParamList,
    Samples,
    XNoiseStd,
    parse_assignments,
    parse_colour,
)
from simulator.physics import PhysicalParameters
from simulator.simulate import Effects, Scenario
from simulator.simulate import simulate as run_simulation


def simulate(
    out: Annotated[Path, typer.Option("--out", help="Output file, .csv or .npz.")],
    fault: Fault = "none",
    k: Magnitude = 0.0,
    n: Samples = 2000,
    seed: Annotated[int | None, typer.Option(help="Random seed (default: fresh entropy).", min=0)] = None,
    excitation_std: ExcitationStd = 25e3,
    disturbance_std: DisturbanceStd = 800.0,
    noise_std: NoiseStd = 0.0,
    x_noise_std: XNoiseStd = 0.0,
    noise_colour: NoiseColour = None,
    effect: EffectList = None,
    param: ParamList = None,
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
        noise_colour=parse_colour(noise_colour),
        effects=Effects.parse(effect or []),
    )
    record = run_simulation(scenario, n, seed)
    path = write_record(out, record.x, record.y, record.fs)
    stdout.print(
        f"wrote {path}: {n} samples at fs = {record.fs:g} Hz, fault {fault} k = {k:g} %, "
        f"std(y) = {record.y.std():.4g} m"
    )
