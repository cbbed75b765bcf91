"""An n-degree-of-freedom chain: masses and springs in series, integrated as the 2-DOF rig is.

    wall ─k1─ m1 ─k2─ m2 ─ … ─kn─ mn ─k(n+1)─ wall,   a damper c_i from each mass to ground

Spring i joins mass i−1 (the wall for i = 1) to mass i; spring n+1 joins mass n to the far wall
and is absent (zero) unless stated. Each spring may carry a cubic part alongside its linear one,
force k_i·d + kc_i·d³ for an elongation d. The force F drives mass 1, as on the rig. With the
elongations d = D·x (D the (n+1)×n incidence matrix) the equations of motion are

    M·ẍ + C·ẋ + Dᵀ·(k⊙d + kc⊙d³) = e1·(F + w),   K = Dᵀ·diag(k)·D,

discretised by the rig's forward differences (SPEC §1). The rig is the chain with n = 2,
k = (k1, k2, 0), kc = (0, 0, k3), c = (c1, c2): its cubic spring grounds mass 2, as spring 3 does.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np

from models.errors import InputError
from simulator.physics import UnstableSimulationError, check_pole_radius
from simulator.simulate import check_levels, excitation, measured_input, measurement_noise
from simulator.temperature import Thermal

Response = Literal["displacement", "acceleration"]
# The healthy samples whose RMS sets a sensor noise floor (:meth:`ChainScenario.with_sensor_noise`).
NOISE_FLOOR_SAMPLES = 20_000
RESPONSES: tuple[Response, ...] = ("displacement", "acceleration")
MAX_MASSES = 50  # a chain's cost grows with n² per step; monitoring studies use a handful
# A chain stands for a structure of one's own: unless one is asked for, no unmeasured force acts
# on it, and its records' noise is its sensors' (``with_sensor_noise``). The rig's unmeasured
# force is the paper's setting (``simulator.study.StudySettings``), not a chain's.
DISTURBANCE_STD = 0.0


@dataclass(frozen=True)
class ChainParameters:
    """Masses m_1 … m_n [kg], spring stiffnesses k_1 … k_{n+1} [N/m] and their cubic parts
    kc_1 … kc_{n+1} [N/m³], dampers c_1 … c_n [N·s/m] to ground, and the step ``ts`` [s]."""

    masses: tuple[float, ...]
    stiffness: tuple[float, ...]
    cubic: tuple[float, ...]
    damping: tuple[float, ...]
    ts: float = 6.666e-4

    def __post_init__(self) -> None:
        n = len(self.masses)
        if not 1 <= n <= MAX_MASSES:
            raise InputError(f"a chain has 1 to {MAX_MASSES} masses, got {n}")
        for name, count in (("stiffness", n + 1), ("cubic", n + 1), ("damping", n)):
            if len(getattr(self, name)) != count:
                raise InputError(
                    f"a chain of {n} masses needs {count} {name} values, got {len(getattr(self, name))}"
                )
        for name in ("masses", "stiffness", "cubic", "damping"):
            for index, value in enumerate(getattr(self, name), start=1):
                if not math.isfinite(value) or value < 0 or (name == "masses" and value == 0):
                    rule = "positive" if name == "masses" else "finite and not negative"
                    raise InputError(f"{name} value {index} must be {rule}, got {value}")
        if not (math.isfinite(self.ts) and self.ts > 0):
            raise InputError(f"the step ts must be positive, got {self.ts}")

    @classmethod
    def build(
        cls,
        n: int,
        masses: Sequence[float],
        stiffness: Sequence[float],
        damping: Sequence[float],
        cubic: Sequence[float] = (0.0,),
        ts: float = 6.666e-4,
    ) -> ChainParameters:
        """Parameters from one value for every element or one per element. A single stiffness or
        cubic value is given to springs 1 … n (none at the far wall); n + 1 values include it."""
        return cls(
            spread(masses, n, "--mass"),
            spread(stiffness, n, "--stiffness", with_end=True),
            spread(cubic, n, "--cubic", with_end=True),
            spread(damping, n, "--damping"),
            ts,
        )

    @property
    def n(self) -> int:
        return len(self.masses)

    @property
    def springs(self) -> list[str]:
        """Spring names k1 … k(n+1): the fault modes and the thermal coefficients' names."""
        return [f"k{i}" for i in range(1, self.n + 2)]

    def spring(self, name: str) -> int:
        """Index of a spring by name, refusing names the chain does not have."""
        if name not in self.springs:
            raise InputError(f"the chain has no spring {name!r}; its springs are {', '.join(self.springs)}")
        return self.springs.index(name)

    def scaled(self, factors: np.ndarray) -> ChainParameters:
        """Each spring, linear and cubic part, multiplied by its factor."""
        return dataclasses.replace(
            self,
            stiffness=tuple(float(v) for v in np.multiply(self.stiffness, factors)),
            cubic=tuple(float(v) for v in np.multiply(self.cubic, factors)),
        )

    def with_fault(self, fault: str, k: float) -> ChainParameters:
        """Spring ``fault`` (linear and cubic part) multiplied by (1 − k/100), as the rig's
        fault modes are: positive k is a reduction (loosening)."""
        if fault == "none":
            return self
        index = self.spring(fault)
        if self.stiffness[index] == 0 and self.cubic[index] == 0:
            raise InputError(
                f"spring {fault} is absent from this chain (zero stiffness): it cannot be faulty"
            )
        if not math.isfinite(k) or k >= 100:
            raise InputError(f"fault magnitude {k} % would remove the spring entirely; use k < 100")
        factors = np.ones(self.n + 1)
        factors[index] = 1 - k / 100
        return self.scaled(factors)

    def at_temperature(self, temperature: float, thermal: Thermal) -> ChainParameters:
        """Every spring's stiffness at ``temperature`` (the stated values hold at the reference)."""
        thermal.check(self.springs)
        return self.scaled(np.array([thermal.factor(name, temperature) for name in self.springs]))

    @cached_property
    def incidence(self) -> np.ndarray:
        """D with elongations d = D·x: d_i = x_i − x_{i−1}, x_0 = 0 (the walls)."""
        D = np.zeros((self.n + 1, self.n))
        D[np.arange(self.n), np.arange(self.n)] = 1.0
        D[np.arange(1, self.n + 1), np.arange(self.n)] = -1.0
        return D

    def stiffness_matrix(self, extra: np.ndarray | float = 0.0) -> np.ndarray:
        """K = Dᵀ·diag(k + extra)·D; ``extra`` adds tangent stiffness to the springs."""
        D = self.incidence
        return D.T @ np.diag(np.add(self.stiffness, extra)) @ D

    def natural_frequencies(self) -> np.ndarray:
        """Undamped linear natural frequencies [Hz], ascending: eigenvalues of M⁻¹K."""
        # Imported here: `narxwatch-sim` loads this module for its options, and most of its
        # commands (and every record of the 2-DOF structure) never ask for the frequencies.
        import scipy.linalg

        eigenvalues = scipy.linalg.eigh(self.stiffness_matrix(), np.diag(self.masses), eigvals_only=True)
        return np.sqrt(np.clip(eigenvalues, 0, None)) / (2 * np.pi)

    def recursion(self, extra: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(A1, A0) of the linear part of the scheme x[t+2] = A1·x[t+1] + A0·x[t] + …"""
        h = self.ts**2 / np.asarray(self.masses)
        damping = np.diag(h * np.asarray(self.damping) / self.ts)
        identity = np.eye(self.n)
        return 2 * identity - damping, -identity + damping - h[:, None] * self.stiffness_matrix(extra)

    def pole_radius(self, amplitude: float = 0.0) -> float:
        """Largest pole modulus of the scheme linearised with every cubic spring at the tangent
        stiffness 3·kc·amplitude² it has at that elongation."""
        A1, A0 = self.recursion(3 * np.asarray(self.cubic) * amplitude**2)
        transition = np.block([[np.zeros((self.n, self.n)), np.eye(self.n)], [A0, A1]])
        return float(np.max(np.abs(np.linalg.eigvals(transition))))

    @cached_property
    def linear_pole_radius(self) -> float:
        return self.pole_radius()

    @cached_property
    def stable_amplitude(self) -> float:
        """Largest elongation (m) of the cubic springs up to which the scheme stays stable."""
        if not any(self.cubic) or self.linear_pole_radius >= 1:
            return np.inf if not any(self.cubic) else 0.0
        low, high = 0.0, 1.0
        while self.pole_radius(high) < 1:
            low, high = high, 2 * high
            if high > 1e6:
                return np.inf
        for _ in range(60):
            middle = 0.5 * (low + high)
            low, high = (middle, high) if self.pole_radius(middle) < 1 else (low, middle)
        return low


def spread(values: Sequence[float], n: int, option: str, with_end: bool = False) -> tuple[float, ...]:
    """One value for every element, or one per element (n, or n + 1 with the far wall's spring)."""
    values = tuple(float(value) for value in values)
    if len(values) == 1:
        return values * n + ((0.0,) if with_end else ())
    if len(values) == n:
        return values + ((0.0,) if with_end else ())
    if with_end and len(values) == n + 1:
        return values
    counts = f"1, {n} or {n + 1}" if with_end else f"1 or {n}"
    raise InputError(f"{option} takes {counts} values for a chain of {n} masses, got {len(values)}")


def check_stable(p: ChainParameters) -> None:
    """Refuse a chain on which the forward-difference scheme diverges from rest."""
    check_pole_radius(
        p.linear_pole_radius,
        p.ts,
        "for this chain",
        ": more damping (--damping), less stiffness or heavier masses",
    )


@dataclass(frozen=True)
class ChainScenario:
    """A simulated record of the chain but its length and seed; fields as the rig's
    :class:`simulator.simulate.Scenario`. ``outputs`` are the measured masses (1-based, all by
    default), each a channel y<mass> of displacement [m] or acceleration [m/s²]."""

    params: ChainParameters
    fault: str = "none"
    k: float = 0.0
    excitation_std: float = 25e3
    disturbance_std: float = DISTURBANCE_STD
    y_noise_std: float = 0.0
    x_noise_std: float = 0.0
    noise_colour: tuple[float, ...] = ()
    burn_in: int = 1500
    temperature: float | None = None
    thermal: Thermal = field(default_factory=Thermal)
    outputs: tuple[int, ...] | None = None
    response: Response = "displacement"

    def __post_init__(self) -> None:
        if self.response not in RESPONSES:
            raise InputError(f"--response {self.response!r}: choose one of {', '.join(RESPONSES)}")

    @property
    def structure(self) -> ChainParameters:
        """The parameters with the fault applied, at the scenario's temperature."""
        faulty = self.params.with_fault(self.fault, self.k)
        return faulty if self.temperature is None else faulty.at_temperature(self.temperature, self.thermal)

    @property
    def measured(self) -> tuple[int, ...]:
        """The measured masses, checked against the chain."""
        masses = tuple(range(1, self.params.n + 1)) if self.outputs is None else self.outputs
        if (
            not masses
            or len(set(masses)) < len(masses)
            or not set(masses) <= set(range(1, self.params.n + 1))
        ):
            raise InputError(
                f"--outputs must name distinct masses of the chain, 1 … {self.params.n}; got "
                f"{', '.join(map(str, masses)) or 'none'}"
            )
        return masses

    @property
    def channels(self) -> tuple[str, ...]:
        """Names of the measured channels, y<mass>."""
        return tuple(f"y{mass}" for mass in self.measured)

    @property
    def fs(self) -> float:
        return float(round(1 / self.params.ts))

    def with_sensor_noise(self, share: float) -> ChainScenario:
        """The scenario with white noise on the force and on each measured channel, ``share`` of
        that signal's RMS when the chain is healthy and noise-free at this excitation: a sensor's
        noise floor, so that a fault changes the response and not the noise added to it."""
        if not 0 <= share < 1:
            raise InputError(f"--noise-share must lie in [0, 1), a share of the RMS; got {share:g}")
        clean = dataclasses.replace(
            self, fault="none", k=0.0, y_noise_std=0.0, x_noise_std=0.0, temperature=None
        )
        responses = simulate_chain(clean, NOISE_FLOOR_SAMPLES, 1).responses.values()
        y_rms = float(np.mean([np.std(channel) for channel in responses]))
        return dataclasses.replace(self, y_noise_std=share * y_rms, x_noise_std=share * self.excitation_std)


@dataclass(frozen=True)
class ChainRecord:
    """The force x [N] on mass 1 and the response channels y<mass> by name."""

    x: np.ndarray
    responses: dict[str, np.ndarray]
    fs: float
    scenario: ChainScenario
    seed: int | np.random.SeedSequence | None

    @property
    def temperature(self) -> float | None:
        return self.scenario.temperature


def simulate_chain(
    scenario: ChainScenario, n: int, seed: int | np.random.SeedSequence | None = None
) -> ChainRecord:
    """Simulate ``n`` samples of the force on mass 1 and the measured masses' responses.

    Random numbers are drawn in the rig's order (excitation, disturbance, noise on x, noise on y)
    with one noise draw per channel in the order of ``outputs``.
    """
    check_levels(scenario, n)
    masses = scenario.measured
    params = scenario.structure
    check_stable(params)
    rng, command, disturbance = excitation(scenario, n, seed)
    total = n + scenario.burn_in
    positions = integrate(params, command + disturbance)
    _check_diverged(params, positions, scenario)
    if scenario.response == "displacement":
        motion = positions[scenario.burn_in : total]
    else:
        motion = np.diff(positions, n=2, axis=0)[scenario.burn_in :] / params.ts**2
    x = measured_input(rng, scenario, command, n)
    responses = {}
    for mass, name in zip(masses, scenario.channels, strict=True):
        channel = motion[:, mass - 1].copy()
        if scenario.y_noise_std:
            channel += measurement_noise(rng, scenario.y_noise_std, scenario.noise_colour, n)
        responses[name] = channel
    return ChainRecord(x, responses, scenario.fs, scenario, seed)


def integrate(p: ChainParameters, force: np.ndarray) -> np.ndarray:
    """March the forward-difference recursion from rest: positions x[t] (rows) for t = 0 … T+1,
    T = len(force), so that the acceleration (x[t+2] − 2x[t+1] + x[t])/Ts² exists for every t < T.

    x[t+2] = A1·x[t+1] + A0·x[t] − Ts²·M⁻¹·(Dᵀ·(kc⊙(D·x[t])³) − e1·F[t])
    """
    A1, A0 = p.recursion()
    h = p.ts**2 / np.asarray(p.masses)
    nonlinear = np.flatnonzero(p.cubic)
    D = p.incidence[nonlinear]
    pull = h[:, None] * D.T * np.asarray(p.cubic)[nonlinear]  # Ts²·M⁻¹·Dᵀ·diag(kc) on those springs
    drive = h[0] * force
    positions = np.zeros((len(force) + 2, p.n))
    previous, current = positions[0], positions[1]
    with np.errstate(over="ignore", invalid="ignore"):  # divergence is caught after the march
        for t in range(len(force)):
            following = A1 @ current + A0 @ previous
            following[0] += drive[t]
            if nonlinear.size:
                following -= pull @ (D @ previous) ** 3
            positions[t + 2] = following
            previous, current = current, following
    return positions


def _check_diverged(p: ChainParameters, positions: np.ndarray, scenario: ChainScenario) -> None:
    limit = p.stable_amplitude
    finite = np.isfinite(positions).all(axis=1)
    elongation = np.abs(positions @ p.incidence[np.flatnonzero(p.cubic)].T)
    beyond = ~finite | (elongation > limit).any(axis=1)
    if not beyond.any():
        return
    first = int(np.argmax(beyond))
    reached = (
        "an infinite value"
        if not finite[first]
        else f"a cubic spring's elongation {elongation[first].max():.3g} m"
    )
    raise UnstableSimulationError(
        f"the simulation diverged: the response reached {reached} at t = {first * p.ts:.3f} s, "
        f"beyond the {limit:.3g} m up to which the explicit scheme is stable with the cubic "
        f"springs' stiffening; lower the excitation (std {scenario.excitation_std:g} N) or the cubic "
        "stiffness"
    )
