"""``narxwatch simulate``: write a simulated record of the 2-DOF rig or of an n-mass chain."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from models.errors import InputError
from recordfiles.writer import channels, write_record
from service.cli.console import stdout
from simulator.chain import ChainScenario, simulate_chain
from simulator.options import (
    ChainOptions,
    CubicValues,
    DampingValues,
    DisturbanceStd,
    EffectList,
    ExcitationStd,
    Fault,
    Magnitude,
    Masses,
    MassValues,
    NoiseColour,
    NoiseShare,
    NoiseStd,
    Outputs,
    ParamList,
    ResponseOption,
    Samples,
    StiffnessValues,
    XNoiseStd,
    disturbance_level,
    parse_assignments,
    parse_colour,
    parse_outputs,
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
    disturbance_std: DisturbanceStd = None,
    noise_std: NoiseStd = 0.0,
    x_noise_std: XNoiseStd = 0.0,
    noise_colour: NoiseColour = None,
    effect: EffectList = None,
    param: ParamList = None,
    masses: Masses = None,
    mass: MassValues = None,
    stiffness: StiffnessValues = None,
    damping: DampingValues = None,
    cubic: CubicValues = None,
    response: ResponseOption = None,
    outputs: Outputs = None,
    noise_share: NoiseShare = None,
) -> None:
    """Simulate excitation x [N] and response y of the 2-DOF rig (SPEC §1) [m], or, with --masses,
    of a chain of masses (a structure that is not the rig) [m or m/s²]."""
    chain = ChainOptions(masses, mass, stiffness, damping, cubic, response).parameters()
    colour = parse_colour(noise_colour)
    if chain is None:
        if noise_share is not None or outputs is not None:
            raise InputError(
                "--noise-share and --outputs are options of the chain: give --masses N (the rig takes "
                "--noise-std and --x-noise-std)"
            )
        params = PhysicalParameters().replace(**parse_assignments(param or [], "parameter"))
        scenario = Scenario(
            params=params,
            fault=fault,  # type: ignore[arg-type]  # checked by with_fault
            k=k,
            excitation_std=excitation_std,
            disturbance_std=disturbance_level(disturbance_std, chain=False),
            y_noise_std=noise_std,
            x_noise_std=x_noise_std,
            noise_colour=colour,
            effects=Effects.parse(effect or []),
        )
        rig = run_simulation(scenario, n, seed)
        x, y, fs, unit = rig.x, rig.y, rig.fs, "m"
    else:
        if effect or param:
            raise InputError(
                "--effect and --param act on the 2-DOF rig; the chain (--masses) takes --mass, "
                "--stiffness, --damping and --cubic"
            )
        chain_scenario = ChainScenario(
            chain,
            fault,
            k,
            excitation_std=excitation_std,
            disturbance_std=disturbance_level(disturbance_std, chain=True),
            y_noise_std=noise_std,
            x_noise_std=x_noise_std,
            noise_colour=colour,
            outputs=parse_outputs(outputs, chain.n),
            response=response or "displacement",  # type: ignore[arg-type]  # checked by ChainScenario
        )
        x, y, fs = chain_signals(chain_scenario, noise_share, n, seed)
        unit = "m/s²" if chain_scenario.response == "acceleration" else "m"
    path = write_record(out, x, y, fs)
    spread = np.mean([np.std(channel) for channel in channels(y).values()])
    stdout.print(
        f"wrote {path}: {n} samples at fs = {fs:g} Hz, fault {fault} k = {k:g} %, "
        f"std(y) = {spread:.4g} {unit}"
    )


def chain_signals(
    scenario: ChainScenario, noise_share: float | None, n: int, seed: int | None
) -> tuple[np.ndarray, np.ndarray | dict[str, np.ndarray], float]:
    """x, the response (one measured mass: the channel ``y``; several: y<mass> by name) and fs of
    a simulated chain record, its sensor noise ``noise_share`` of the healthy RMS if given."""
    if noise_share is not None:
        if scenario.y_noise_std or scenario.x_noise_std:
            raise InputError(
                "--noise-share sets the sensor noise: give it or --noise-std/--x-noise-std, not both"
            )
        scenario = scenario.with_sensor_noise(noise_share)
    record = simulate_chain(scenario, n, seed)
    responses = record.responses
    return record.x, (next(iter(responses.values())) if len(responses) == 1 else responses), record.fs
