"""Which records ``narxwatch-sim`` makes and when: the scenario options turned into scenarios, the
paper's cases, and streams whose fault develops over acquisition time."""

from __future__ import annotations

import datetime as dt
import enum
import itertools
import secrets
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from models.errors import InputError
from simulator import chain
from simulator.chain import ChainRecord, ChainScenario, simulate_chain
from simulator.options import (
    ChainOptions,
    disturbance_level,
    parse_assignments,
    parse_colour,
    parse_outputs,
)
from simulator.physics import PhysicalParameters, check_stable
from simulator.simulate import Effects, Scenario, SimulatedRecord, simulate
from simulator.study import CASES
from simulator.temperature import TemperatureCycle, Thermal

SCENARIO_NAMES = [case.name for case in CASES] + ["all", "any"]

AnyScenario = Scenario | ChainScenario
AnyRecord = SimulatedRecord | ChainRecord


@dataclass(frozen=True)
class ScenarioOptions:
    """The scenario options as given, turned into checked scenarios for any fault and magnitude.

    ``climate`` gives each record its temperature from its acquisition time; ``chain`` the
    n-mass chain's options (the 2-DOF rig without ``--masses``).
    """

    excitation_std: float
    disturbance_std: float | None  # None: the structure's own (``options.disturbance_level``)
    noise_std: float
    x_noise_std: float
    effects: tuple[str, ...]
    params: tuple[str, ...]
    noise_colour: str | None = None
    climate: TemperatureCycle | None = None
    thermal: tuple[str, ...] = ()
    outputs: str | None = None
    chain: ChainOptions = field(default_factory=ChainOptions)

    def temperature(self, when: dt.datetime) -> float | None:
        return None if self.climate is None else self.climate.at(when)

    def scenario(self, fault: str, k: float, temperature: float | None = None) -> AnyScenario:
        """A scenario refused now, before anything is posted, if its options cannot be simulated."""
        if self.thermal and self.climate is None:
            raise InputError("--thermal-coefficient acts only at a temperature: give it with --temperature")
        thermal = Thermal(parse_assignments(self.thermal, "thermal coefficient"))
        k = 0.0 if fault == "none" else k
        parameters = self.chain.parameters()
        levels = {
            "excitation_std": self.excitation_std,
            "disturbance_std": disturbance_level(self.disturbance_std, chain=parameters is not None),
            "y_noise_std": self.noise_std,
            "x_noise_std": self.x_noise_std,
            "noise_colour": parse_colour(self.noise_colour),
            "temperature": temperature,
            "thermal": thermal,
        }
        if parameters is not None:
            if self.effects or self.params:
                raise InputError(
                    "--effect and --param act on the 2-DOF rig; the chain (--masses) takes --mass, "
                    "--stiffness, --damping and --cubic"
                )
            scenario = ChainScenario(
                parameters,
                fault,
                k,
                outputs=parse_outputs(self.outputs, parameters.n),
                response=self.chain.response or "displacement",  # type: ignore[arg-type]  # checked by it
                **levels,
            )
            chain.check_stable(scenario.structure)
        else:
            scenario = Scenario(
                params=PhysicalParameters().replace(**parse_assignments(self.params, "parameter")),
                fault=fault,  # type: ignore[arg-type]  # checked by with_fault below
                k=k,
                effects=Effects.parse(self.effects),
                outputs=parse_outputs(self.outputs, 2) or (2,),
                **levels,
            )
            check_stable(scenario.structure)
        return scenario


@dataclass(frozen=True)
class Plan:
    """One record to make and deliver; ``case`` groups records for the tally."""

    case: str
    scenario: AnyScenario
    n: int
    seed: int
    acquired_at: dt.datetime

    def describe(self) -> str:
        scenario = self.scenario
        described = f"simulated {truth(scenario)}"
        if isinstance(scenario, Scenario) and scenario.effects.describe():
            effects = scenario.effects.describe().items()
            described += " with " + ", ".join(f"{name}={value:g}" for name, value in effects)
        if scenario.temperature is not None:
            described += f" at {scenario.temperature:.1f} °C"
        return f"{described}, seed {self.seed}"

    def simulate(self) -> AnyRecord:
        if isinstance(self.scenario, ChainScenario):
            return simulate_chain(self.scenario, self.n, self.seed)
        return simulate(self.scenario, self.n, self.seed)


def truth(scenario: AnyScenario) -> str:
    return "healthy" if scenario.fault == "none" else f"{scenario.fault} {scenario.k:g} %"


def first_seed(seed: int | None) -> int:
    """The given seed, or a fresh one small enough to retype into ``narxwatch simulate --seed``."""
    return secrets.randbelow(2**31) if seed is None else seed


def start_time(text: str | None) -> dt.datetime | None:
    """``--acquired-at`` as an aware datetime; a naive time is refused, as the service refuses it."""
    if text is None:
        return None
    try:
        moment = dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(
            f"--acquired-at {text!r} is not an ISO 8601 time, e.g. 2026-11-21T10:00:00Z"
        ) from None
    if moment.tzinfo is None:
        raise InputError(f"--acquired-at {text!r} needs a timezone, e.g. 2026-11-21T10:00:00Z")
    return moment


def now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(microsecond=0)


class Course(enum.StrEnum):
    """How a stream's fault develops over acquisition time (``--scenario``), for testing alarm rules."""

    healthy = "healthy"  # no fault at all
    step = "step"  # --k from --onset on
    drift = "drift"  # growing at --rate % a day from --onset on
    intermittent = "intermittent"  # --k in each record from --onset on with probability --duty


SECONDS_PER_DAY = 86400.0


@dataclass(frozen=True)
class Stream:
    """Records due every ``every`` seconds, acquired ``spacing`` seconds apart (``every`` unless
    ``--per-day`` is given), whose fault follows ``course`` or, without one, grows by ``drift`` per record."""

    options: ScenarioOptions
    fault: str
    k: float
    drift: float
    n: int
    seed: int
    every: float
    count: int | None
    start: dt.datetime | None
    course: Course | None = None
    onset: float = 0.0
    rate: float = 0.0
    duty: float = 0.5
    per_day: float | None = None
    wait: bool = True

    @property
    def mode(self) -> str:
        """The faulty mode: the one given, or k2 when none is but a fault is asked for."""
        if self.fault != "none" or self.course is Course.healthy:
            return self.fault
        return "k2" if self.drift or self.course is not None else self.fault

    @property
    def spacing(self) -> float:
        """Seconds of acquisition time between records."""
        return self.every if self.per_day is None else SECONDS_PER_DAY / self.per_day

    def fault_at(self, index: int) -> tuple[str, float]:
        """The fault mode and magnitude [%] of record ``index``; a record without fault is ("none", 0)."""
        if self.course is None:
            return self.mode, self.k + index * self.drift
        days = index * self.spacing / SECONDS_PER_DAY
        if self.course is Course.healthy or days < self.onset:
            return "none", 0.0
        if self.course is Course.step:
            return self.mode, self.k
        if self.course is Course.drift:
            grown = self.rate * (days - self.onset)
            return (self.mode, grown) if grown else ("none", 0.0)
        # Whether the fault shows in this record is drawn from the record's own seed, so that
        # `narxwatch simulate --seed` and the manifest tell the same story.
        shows = np.random.default_rng([self.seed + index, 1]).random() < self.duty
        return (self.mode, self.k) if shows else ("none", 0.0)

    def check(self) -> None:
        """Refuse now a stream whose options do not fit its course, or whose first or last record
        could not be simulated, at the coldest and the warmest temperature of its cycle."""
        self.check_course()
        climate = self.options.climate
        temperatures = [None] if climate is None else climate.extremes
        faults = [self.fault_at(0)]
        if self.count is not None:
            faults.append(self.fault_at(self.count - 1))
            if self.course in (Course.step, Course.intermittent):
                faults.append((self.mode, self.k))
        for fault in faults:
            for temperature in temperatures:
                self.options.scenario(*fault, temperature)

    def check_course(self) -> None:
        if self.per_day is not None and not self.per_day > 0:
            raise InputError(f"--per-day must be positive; got {self.per_day:g}")
        if self.course is None:
            for name, given in (("--onset", self.onset), ("--rate", self.rate)):
                if given:
                    raise InputError(f"{name} belongs to a --scenario (step, drift or intermittent)")
            return
        if self.drift:
            raise InputError(
                "--drift grows k per record without a --scenario; with one, use --scenario drift --rate"
            )
        if self.course is Course.healthy and (self.fault != "none" or self.k):
            raise InputError("--scenario healthy simulates no fault: leave out --fault and --k")
        if self.course in (Course.step, Course.intermittent) and not self.k:
            raise InputError(f"--scenario {self.course} needs the fault's size: give --k (percent)")
        if self.course is Course.drift:
            if self.k:
                raise InputError("--scenario drift starts from no fault at --onset: give --rate, not --k")
            if not self.rate:
                raise InputError("--scenario drift needs its growth: give --rate (percent a day)")
        elif self.rate:
            raise InputError("--rate belongs to --scenario drift")
        if self.onset < 0:
            raise InputError(f"--onset is days after the first record; got {self.onset:g}")
        if not 0 < self.duty <= 1:
            raise InputError(
                f"--duty is the share of records that show the fault, in (0, 1]; got {self.duty:g}"
            )

    def plans(self) -> Iterator[Plan]:
        began = time.monotonic()
        # Real time stamps each record as it is sent, unless --per-day sets the acquisitions' pace.
        origin = self.start or (now() if self.per_day is not None else None)
        indices = itertools.count() if self.count is None else range(self.count)
        for index in indices:
            if self.wait:
                time.sleep(max(0.0, began + index * self.every - time.monotonic()))
            when = now() if origin is None else origin + dt.timedelta(seconds=index * self.spacing)
            scenario = self.options.scenario(*self.fault_at(index), self.options.temperature(when))
            yield Plan("stream", scenario, self.n, self.seed + index, when)


def chosen_cases(
    name: str, fault: str | None, k: float | None, options: ScenarioOptions, temperature: float | None = None
) -> list[tuple[str, AnyScenario]]:
    """The named paper case(s) with their fault and magnitude, or ``any`` with the given ones."""
    name = name.strip()
    name = name.lower() if name.lower() in ("all", "any") else name.upper()
    if name == "any":
        scenario = options.scenario(fault or "none", k or 0.0, temperature)
        return [(f"case any ({truth(scenario)})", scenario)]
    if fault is not None or k is not None:
        raise InputError(f"case {name} fixes the fault and its magnitude: use 'any' for --fault and --k")
    chosen = [case for case in CASES if name in (case.name, "all")]
    if not chosen:
        raise InputError(f"unknown scenario {name!r}: choose one of {', '.join(SCENARIO_NAMES)}")
    return [
        (f"case {case.name} ({case.description})", options.scenario(case.fault, case.true_k, temperature))
        for case in chosen
    ]
