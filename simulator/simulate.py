"""Simulated records of the 2-DOF structure: excitation, noise, faults and undeclared effects.

The declared model (SPEC §2) knows only the linear springs and dampers and the cubic spring.
:class:`Effects` adds physics it does not know, each switched on by a name and a size, so that
diagnostics can be tested against effects whose truth is known.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Protocol

import numpy as np

from models.errors import InputError
from simulator.physics import (
    FaultMode,
    PhysicalParameters,
    UnstableSimulationError,
    check_stable,
)
from simulator.temperature import Thermal

# Undeclared effects by name: (field, unit, meaning). ``sine`` takes AMPLITUDE@FREQUENCY.
MAX_NOISE_COLOUR = 50  # moving-average coefficients of the measurement noise
EFFECTS: dict[str, tuple[str, str]] = {
    "coulomb1": ("N", "Coulomb friction on mass 1, force level"),
    "coulomb2": ("N", "Coulomb friction on mass 2, force level"),
    "quadratic_damping1": ("N·s²/m²", "quadratic damping c·v·|v| on mass 1"),
    "quadratic_damping2": ("N·s²/m²", "quadratic damping c·v·|v| on mass 2"),
    "quadratic_stiffness1": ("N/m²", "asymmetric spring force k·x1² on mass 1"),
    "quadratic_stiffness2": ("N/m²", "asymmetric spring force k·x2² on mass 2"),
    "offset": ("m", "constant offset of the y sensor"),
    "sine": ("N@Hz", "unmeasured sinusoidal force on mass 1, AMPLITUDE@FREQUENCY"),
    "saturation": ("N", "the actuator clips the applied force at ±size; x records the command"),
    "dead_zone": ("N", "the actuator applies nothing within ±size of a zero command, command ∓ size beyond"),
    "backlash": ("N", "the actuator's force trails the command through a play of ±size (gear backlash)"),
    "sensor_range": ("m", "the y sensor saturates at ±size: y plateaus at the range ends"),
    "power_damping2": ("N·(s/m)^½", "orifice-like damping c·√|v|·sign v on mass 2"),
    "hertz_contact2": ("N/m^1.5", "Hertzian contact spring k·|x2|^1.5·sign x2 on mass 2"),
    "hysteresis2": (
        "N/m",
        f"Bouc–Wen hysteretic spring k·z on mass 2, dz = dx2 − β|dx2|z − γ·dx2|z|, β = γ = {1 / 0.1:g}/m",
    ),
    "cubic_stiffness1": ("N/m³", "cubic spring k·x1³ on the unmeasured mass 1"),
}
# The Bouc–Wen variable z of "hysteresis2" saturates at 1/(β + γ) = 5 cm, within the response's
# range at the default excitation (std(y) ≈ 8 cm): its loops are wide, not a linear spring.
BOUC_WEN_BETA = BOUC_WEN_GAMMA = 10.0


@dataclass(frozen=True)
class Effects:
    """Effects the declared model does not contain; zero means off."""

    coulomb1: float = 0.0
    coulomb2: float = 0.0
    quadratic_damping1: float = 0.0
    quadratic_damping2: float = 0.0
    quadratic_stiffness1: float = 0.0
    quadratic_stiffness2: float = 0.0
    offset: float = 0.0
    sine_amplitude: float = 0.0
    sine_frequency: float = 0.0
    saturation: float = 0.0
    dead_zone: float = 0.0
    backlash: float = 0.0
    sensor_range: float = 0.0
    power_damping2: float = 0.0
    hertz_contact2: float = 0.0
    hysteresis2: float = 0.0
    cubic_stiffness1: float = 0.0

    @classmethod
    def parse(cls, specs: Iterable[str]) -> Effects:
        """Effects from ``NAME=SIZE`` strings, e.g. ``coulomb2=40`` or ``sine=800@12.5``."""
        values: dict[str, float] = {}
        for spec in specs:
            name, sep, size = spec.partition("=")
            name = name.strip()
            if not sep or name not in EFFECTS:
                raise InputError(
                    f"cannot read effect {spec!r}: write NAME=SIZE with NAME one of "
                    f"{', '.join(EFFECTS)} (sine takes AMPLITUDE@FREQUENCY)"
                )
            try:
                if name == "sine":
                    amplitude, at, frequency = size.partition("@")
                    if not at:
                        raise ValueError
                    values["sine_amplitude"], values["sine_frequency"] = float(amplitude), float(frequency)
                else:
                    values[name] = float(size)
            except ValueError:
                raise InputError(f"effect {spec!r}: the size is not a number ({EFFECTS[name][0]})") from None
        effects = cls(**values)
        for key, value in dataclasses.asdict(effects).items():
            if not math.isfinite(value):
                raise InputError(f"effect {key} must be a finite number, got {value}")
        for name in ("saturation", "sine_frequency", "dead_zone", "backlash", "sensor_range"):
            if getattr(effects, name) < 0:
                raise InputError(f"{name.replace('_', ' ')} cannot be negative")
        return effects

    @property
    def acts_on_state(self) -> bool:
        return any(
            (
                self.coulomb1,
                self.coulomb2,
                self.quadratic_damping1,
                self.quadratic_damping2,
                self.quadratic_stiffness1,
                self.quadratic_stiffness2,
                self.power_damping2,
                self.hertz_contact2,
                self.hysteresis2,
                self.cubic_stiffness1,
            )
        )

    def applied_force(self, command: np.ndarray) -> np.ndarray:
        """The force the actuator applies for the commanded one: clipped, through a dead zone,
        through backlash, in that order."""
        force = np.clip(command, -self.saturation, self.saturation) if self.saturation else command
        if self.dead_zone:
            force = force - np.clip(force, -self.dead_zone, self.dead_zone)
        if self.backlash:
            # Imported here: models.terms loads numba, which a process that simulates no backlash
            # (every `narxwatch-sim` and `narxwatch simulate` without it) need not load at start.
            from models.terms import play

            force = play(force, self.backlash)
        return force

    def describe(self) -> dict[str, float]:
        return {key: value for key, value in dataclasses.asdict(self).items() if value}


@dataclass(frozen=True)
class Scenario:
    """Everything that defines a simulated record but its length and random seed.

    Standard deviations are in newtons (forces) and metres (y); ``burn_in`` samples are
    simulated and dropped so that records start in steady state.
    """

    params: PhysicalParameters = field(default_factory=PhysicalParameters)
    fault: FaultMode = "none"
    k: float = 0.0
    excitation_std: float = 25e3
    disturbance_std: float = 0.0
    y_noise_std: float = 0.0
    x_noise_std: float = 0.0
    # Moving-average colour c_1 … c_q of the measurement noise: each sensor's noise is
    # n[t] = ξ[t] + Σ c_i ξ[t−i] with ξ white of the std above (empty: white noise).
    noise_colour: tuple[float, ...] = ()
    effects: Effects = field(default_factory=Effects)
    burn_in: int = 1500
    # The structure's temperature [°C]; None: the stated stiffnesses hold (no thermal effect).
    temperature: float | None = None
    thermal: Thermal = field(default_factory=Thermal)
    # Measured masses: (2,) is the SPEC's single response y = x2; any other choice, e.g. (1, 2),
    # gives one channel per mass named y1, y2 (sensor effects act on each).
    outputs: tuple[int, ...] = (2,)

    @cached_property
    def structure(self) -> PhysicalParameters:
        """The physical parameters with the fault applied, at the scenario's temperature (once:
        their stability bound costs ~8 ms, and a Monte Carlo simulates one scenario thousands of
        times)."""
        faulty = self.params.with_fault(self.fault, self.k)
        return faulty if self.temperature is None else faulty.at_temperature(self.temperature, self.thermal)

    @property
    def fs(self) -> float:
        return float(round(1 / self.params.ts))

    @property
    def channels(self) -> tuple[str, ...]:
        """Names of the measured channels: ``y`` for mass 2 alone (SPEC §1), else y<mass>."""
        if self.outputs == (2,):
            return ("y",)
        if not self.outputs or len(set(self.outputs)) < len(self.outputs) or not set(self.outputs) <= {1, 2}:
            raise InputError(
                f"--outputs must name distinct masses of the 2-DOF rig, 1 or 2; got "
                f"{', '.join(map(str, self.outputs)) or 'none'}"
            )
        return tuple(f"y{mass}" for mass in self.outputs)


@dataclass(frozen=True)
class SimulatedRecord:
    """``y`` is mass 2's measured displacement; ``responses`` every measured channel by name
    (``{"y": y}`` unless the scenario measures other masses)."""

    x: np.ndarray
    y: np.ndarray
    fs: float
    scenario: Scenario
    seed: int | np.random.SeedSequence | None
    responses: dict[str, np.ndarray]

    @property
    def temperature(self) -> float | None:
        return self.scenario.temperature


def simulate(scenario: Scenario, n: int, seed: int | np.random.SeedSequence | None = None) -> SimulatedRecord:
    """Simulate ``n`` samples of measured excitation x (N) and response y (m)."""
    check_levels(scenario, n)
    names = scenario.channels
    params = scenario.structure
    check_stable(params)
    rng, command, disturbance = excitation(scenario, n, seed)
    total = n + scenario.burn_in
    effects = scenario.effects
    force = effects.applied_force(command) + disturbance
    if effects.sine_amplitude:
        time = np.arange(total) * params.ts
        phase = rng.uniform(0, 2 * np.pi)
        force = force + effects.sine_amplitude * np.sin(2 * np.pi * effects.sine_frequency * time + phase)
    x1, x2 = _integrate(params, force, effects)
    _check_diverged(params, x1, x2, scenario)
    x = measured_input(rng, scenario, command, n)
    y = x2[scenario.burn_in :] + effects.offset
    if scenario.y_noise_std:
        y += measurement_noise(rng, scenario.y_noise_std, scenario.noise_colour, n)
    if effects.sensor_range:
        y = np.clip(y, -effects.sensor_range, effects.sensor_range)
    if names == ("y",):
        return SimulatedRecord(x, y, scenario.fs, scenario, seed, {"y": y})
    # Mass 1's sensor draws its noise after mass 2's, so that y is the single-output record's.
    y1 = x1[scenario.burn_in :] + effects.offset
    if scenario.y_noise_std:
        y1 += measurement_noise(rng, scenario.y_noise_std, scenario.noise_colour, n)
    if effects.sensor_range:
        y1 = np.clip(y1, -effects.sensor_range, effects.sensor_range)
    measured = {"y1": y1, "y2": y}
    return SimulatedRecord(x, y, scenario.fs, scenario, seed, {name: measured[name] for name in names})


class Levels(Protocol):
    """What :func:`check_levels` reads of a scenario, the rig's or the chain's (``simulator.chain``)."""

    @property
    def burn_in(self) -> int: ...
    @property
    def excitation_std(self) -> float: ...
    @property
    def disturbance_std(self) -> float: ...
    @property
    def y_noise_std(self) -> float: ...
    @property
    def x_noise_std(self) -> float: ...
    @property
    def noise_colour(self) -> tuple[float, ...]: ...


def check_levels(scenario: Levels, n: int) -> None:
    """Refuse a record length, excitation or noise that cannot be simulated."""
    if n < 1:
        raise InputError(f"a record needs at least one sample, got n = {n}")
    for name in ("excitation_std", "disturbance_std", "y_noise_std", "x_noise_std"):
        value = getattr(scenario, name)
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a finite, non-negative number, got {value}")
    if len(scenario.noise_colour) > MAX_NOISE_COLOUR or not all(map(math.isfinite, scenario.noise_colour)):
        raise InputError(
            f"noise_colour takes at most {MAX_NOISE_COLOUR} finite moving-average coefficients, "
            f"got {scenario.noise_colour}"
        )


def excitation(
    scenario: Levels, n: int, seed: int | np.random.SeedSequence | None
) -> tuple[np.random.Generator, np.ndarray, np.ndarray | float]:
    """The record's random numbers as they are drawn first, over the burn-in and the record: the
    commanded force and the unmeasured disturbance (0 where there is none), with the generator
    that draws the rest after them."""
    rng = np.random.default_rng(seed)
    total = n + scenario.burn_in
    command = rng.normal(0.0, scenario.excitation_std, total)
    disturbance = rng.normal(0.0, scenario.disturbance_std, total) if scenario.disturbance_std else 0.0
    return rng, command, disturbance


def measured_input(rng: np.random.Generator, scenario: Levels, command: np.ndarray, n: int) -> np.ndarray:
    """The commanded force after the burn-in as its sensor reads it: with its noise, if any."""
    x = command[scenario.burn_in :].copy()
    if scenario.x_noise_std:
        x += measurement_noise(rng, scenario.x_noise_std, scenario.noise_colour, n)
    return x


def measurement_noise(rng: np.random.Generator, std: float, colour: tuple[float, ...], n: int) -> np.ndarray:
    """n samples of white noise of ``std``, coloured by the moving average 1 + Σ c_i q⁻ⁱ."""
    white = rng.normal(0.0, std, n + len(colour))
    return np.convolve(white, np.concatenate(([1.0], colour)), mode="valid") if colour else white


def _integrate(p: PhysicalParameters, force: np.ndarray, effects: Effects) -> tuple[np.ndarray, np.ndarray]:
    """March the forward-difference recursion; returns x1[t] and x2[t] for t = 0 … len(force)−1."""
    ts, h1, h2 = p.ts, p.ts**2 / p.m1, p.ts**2 / p.m2
    a1, b1, c1 = 2 - h1 * p.c1 / ts, -1 + h1 * p.c1 / ts - h1 * (p.k1 + p.k2), h1 * p.k2
    a2, b2, c2, d2 = 2 - h2 * p.c2 / ts, -1 + h2 * p.c2 / ts - h2 * p.k2, h2 * p.k2, h2 * p.k3
    drive = (h1 * force).tolist()
    n = len(drive)
    out1, out2 = [0.0] * n, [0.0] * n
    state_effects = effects.acts_on_state
    fc1, fc2 = effects.coulomb1, effects.coulomb2
    cq1, cq2 = effects.quadratic_damping1, effects.quadratic_damping2
    kq1, kq2 = effects.quadratic_stiffness1, effects.quadratic_stiffness2
    kc1, cp2, kh2 = effects.cubic_stiffness1, effects.power_damping2, effects.hysteresis2
    kp2 = effects.hertz_contact2
    # (u, u_next) = (x1[t], x1[t+1]) and (w, w_next) = (x2[t], x2[t+1]); both start at rest, as
    # does the Bouc–Wen variable z[t] of mass 2's hysteretic spring.
    u = u_next = w = w_next = z = 0.0
    for t in range(n):
        out1[t] = u
        out2[t] = w
        u_new = a1 * u_next + b1 * u + c1 * w + drive[t]
        w_new = a2 * w_next + b2 * w + c2 * u - d2 * w * w * w
        if state_effects:
            v1, v2 = (u_next - u) / ts, (w_next - w) / ts
            u_new -= h1 * (fc1 * ((v1 > 0) - (v1 < 0)) + cq1 * v1 * abs(v1) + kq1 * u * u + kc1 * u * u * u)
            w_new -= h2 * (
                fc2 * ((v2 > 0) - (v2 < 0))
                + cq2 * v2 * abs(v2)
                + kq2 * w * w
                + cp2 * math.copysign(math.sqrt(abs(v2)), v2)
                + kp2 * math.copysign(abs(w) ** 1.5, w)
                + kh2 * z
            )
            # Bouc–Wen (n = 1) by the same forward difference: dz = dx2 − β|dx2|z − γ·dx2|z|.
            step = w_next - w
            z += step - BOUC_WEN_BETA * abs(step) * z - BOUC_WEN_GAMMA * step * abs(z)
        u, u_next = u_next, u_new
        w, w_next = w_next, w_new
    return np.array(out1), np.array(out2)


def _check_diverged(p: PhysicalParameters, x1: np.ndarray, x2: np.ndarray, scenario: Scenario) -> None:
    limit = p.stable_amplitude
    finite = np.isfinite(x1) & np.isfinite(x2)
    beyond = ~finite | (np.abs(x2) > limit)
    if not beyond.any():
        return
    first = int(np.argmax(beyond))
    reached = "an infinite value" if not finite[first] else f"|x2| = {abs(x2[first]):.3g} m"
    raise UnstableSimulationError(
        f"the simulation diverged: the response reached {reached} at t = {first * p.ts:.3f} s, "
        f"beyond the {limit:.3g} m up to which the explicit scheme is stable with the cubic "
        f"spring's stiffening; lower the excitation (std {scenario.excitation_std:g} N) or the "
        "effects driving it"
    )
