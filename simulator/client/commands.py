"""The ``narxwatch-sim`` commands. The options they share are defined once, as the fields of an
option group (:class:`SimulationOptions`, :class:`~simulator.client.destinations.Target`), which
:func:`~simulator.client.groups.expanded` spreads into each command's options; ``stream``'s own,
how its records follow one another, are a group too (:class:`StreamOptions`)."""

from __future__ import annotations

import datetime as dt
import itertools
import signal
from dataclasses import dataclass
from typing import Annotated, NoReturn

import typer

from models.errors import InputError
from simulator.client.destinations import (
    EXIT_SERVICE_ERROR,
    Report,
    Target,
    deliver_all,
    deliver_stream,
    open_destination,
    stderr,
)
from simulator.client.groups import expanded
from simulator.client.http import ServiceError
from simulator.client.scheduler import (
    Course,
    Plan,
    ScenarioOptions,
    Stream,
    chosen_cases,
    first_seed,
    now,
    start_time,
)
from simulator.client.structures import register
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
    NoiseStd,
    Outputs,
    ParamList,
    ResponseOption,
    Samples,
    StiffnessValues,
    Temperature,
    ThermalList,
    XNoiseStd,
)
from simulator.study import StudySettings
from simulator.temperature import TemperatureCycle

EXIT_INPUT_ERROR = 2
# The option defaults are the study's, so that the paper's cases are simulated as in the paper.
STUDY = StudySettings()

Seed = Annotated[
    int | None,
    typer.Option(min=0, help="Seed of the first record; the next ones use seed + 1, … (default: fresh)."),
]
AcquiredAt = Annotated[
    str | None,
    typer.Option(help="Acquisition time, ISO 8601 with a zone, e.g. 2026-11-21T10:00:00Z (default: now)."),
]
JsonLines = Annotated[bool, typer.Option("--json", help="Print each verdict as one line of JSON.")]


@dataclass(frozen=True)
class SimulationOptions:
    """The record length, seed and scenario options every command takes, as given."""

    n: Samples = STUDY.inspection_samples
    seed: Seed = None
    excitation_std: ExcitationStd = STUDY.excitation_std
    disturbance_std: DisturbanceStd = None  # the structure's own
    noise_std: NoiseStd = 0.0
    x_noise_std: XNoiseStd = 0.0
    noise_colour: NoiseColour = None
    effect: EffectList = None
    param: ParamList = None
    temperature: Temperature = None
    thermal_coefficient: ThermalList = None
    outputs: Outputs = None
    masses: Masses = None
    mass: MassValues = None
    stiffness: StiffnessValues = None
    damping: DampingValues = None
    cubic: CubicValues = None
    response: ResponseOption = None

    def options(self, daily_amplitude: float = 0.0, seasonal_amplitude: float = 0.0) -> ScenarioOptions:
        """The options checked into scenarios; with a temperature, its daily and seasonal cycle."""
        return ScenarioOptions(
            self.excitation_std,
            self.disturbance_std,
            self.noise_std,
            self.x_noise_std,
            tuple(self.effect or ()),
            tuple(self.param or ()),
            self.noise_colour,
            None
            if self.temperature is None
            else TemperatureCycle(self.temperature, daily_amplitude, seasonal_amplitude),
            tuple(self.thermal_coefficient or ()),
            self.outputs,
            ChainOptions(self.masses, self.mass, self.stiffness, self.damping, self.cubic, self.response),
        )


@dataclass(frozen=True)
class StreamOptions:
    """How a stream's records follow one another, as given: their pace, how many, and how the
    fault develops from one to the next (:class:`~simulator.client.scheduler.Stream`)."""

    every: Annotated[float, typer.Option(min=0, help="Seconds between records.")] = 5.0
    count: Annotated[int | None, typer.Option(min=1, help="Records to send (default: until Ctrl-C).")] = None
    drift: Annotated[
        float,
        typer.Option(help="Growth of k per record [%]; grows the --fault mode, or k2 if there is none."),
    ] = 0.0
    scenario: Annotated[
        Course | None,
        typer.Option(
            help="How the fault develops in acquisition time: healthy (none), step (--k from --onset), "
            "drift (--rate % a day from --onset), intermittent (--k in a --duty share of the records "
            "from --onset). Default: --fault at --k growing by --drift a record."
        ),
    ] = None
    onset: Annotated[
        float, typer.Option(help="Days of acquisition time after the first record when the fault begins.")
    ] = 0.0
    rate: Annotated[float, typer.Option(help="Growth of k for --scenario drift [% a day].")] = 0.0
    duty: Annotated[
        float, typer.Option(help="Share of records showing the fault for --scenario intermittent.")
    ] = 0.5
    per_day: Annotated[
        float | None,
        typer.Option(
            help="Records per day of acquisition time: stamps 24 h / PER_DAY apart, whatever --every "
            "(default: --every seconds apart)."
        ),
    ] = None

    def stream(
        self,
        options: ScenarioOptions,
        fault: str,
        k: float,
        simulation: SimulationOptions,
        start: dt.datetime | None,
        wait: bool,
    ) -> Stream:
        """The stream of records of these ``options``, from ``start`` (None: real time)."""
        return Stream(
            options,
            fault,
            k,
            self.drift,
            simulation.n,
            first_seed(simulation.seed),
            self.every,
            self.count,
            start,
            self.scenario,
            self.onset,
            self.rate,
            self.duty,
            self.per_day,
            wait,
        )


@dataclass(frozen=True)
class Posting:
    """When the records of ``record`` and ``scenario`` were acquired and how their verdicts print,
    as given; ``stream`` paces its records and so has options of its own for both."""

    acquired_at: AcquiredAt = None
    json_lines: JsonLines = False

    def start(self) -> dt.datetime:
        """The records' acquisition time: the one given, else now."""
        return start_time(self.acquired_at) or now()

    def post(self, plans: list[Plan], simulation: SimulationOptions, target: Target) -> Report:
        """Every plan's record posted (or written) in turn, each scenario first checked against
        the target; the report of their verdicts."""
        for plan in plans:
            target.check(plan.scenario)
        report = Report(self.json_lines)
        with open_destination(target, simulation.temperature is not None) as destination:
            deliver_all(plans, destination, report)
        return report


# --- The command line ---------------------------------------------------------------------------

app = typer.Typer(
    name="narxwatch-sim",
    help="Post simulated records of the 2-DOF structure to a narxwatch service and print the verdicts.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,  # help texts hold units like [m], which rich markup would swallow
)


@app.command("record")
@expanded
def record_command(
    *,
    fault: Fault = "none",
    k: Magnitude = 0.0,
    simulation: SimulationOptions,
    target: Target,
    posting: Posting,
) -> None:
    """Simulate one record, post it for inspection and print its verdict."""
    options = simulation.options()
    when = posting.start()
    scenario = options.scenario(fault, k, simulation.temperature)
    posting.post(
        [Plan("record", scenario, simulation.n, first_seed(simulation.seed), when)], simulation, target
    )


@app.command("scenario")
@expanded
def scenario_command(
    *,
    name: Annotated[
        str,
        typer.Argument(
            help="A paper case (I healthy, II k2 3 %, III k2 29 %, IV k1 30 %), 'all' four, "
            "or 'any' for the fault given by --fault and --k."
        ),
    ],
    runs: Annotated[int, typer.Option(min=1, help="Records per case.")] = STUDY.runs,
    fault: Annotated[str | None, typer.Option(help="Fault mode for 'any': none, k1, k2.")] = None,
    k: Annotated[float | None, typer.Option(help="Fault magnitude in percent for 'any'.")] = None,
    simulation: SimulationOptions,
    target: Target,
    posting: Posting,
) -> None:
    """Post --runs records of a paper test case (all at one acquisition time) and tally the verdicts."""
    options = simulation.options()
    cases = chosen_cases(name, fault, k, options, simulation.temperature)
    seeds = itertools.count(first_seed(simulation.seed))
    when = posting.start()
    plans = [
        Plan(case, scenario, simulation.n, next(seeds), when) for case, scenario in cases for _ in range(runs)
    ]
    posting.post(plans, simulation, target).tally()


@app.command("stream")
@expanded
def stream_command(
    *,
    streaming: StreamOptions,
    fault: Fault = "none",
    k: Magnitude = 0.0,
    simulation: SimulationOptions,
    target: Target,
    acquired_at: Annotated[
        str | None,
        typer.Option(
            help="Time of the first record, the next ones --every seconds (or 24 h / --per-day) later "
            "(default: real time)."
        ),
    ] = None,
    daily_amplitude: Annotated[
        float,
        typer.Option(
            help="Daily temperature amplitude [°C] about --temperature, warmest at 15:00 of the acquisition "
            "time's zone (half the day's swing)."
        ),
    ] = 0.0,
    seasonal_amplitude: Annotated[
        float,
        typer.Option(
            help="Seasonal temperature amplitude [°C] about --temperature, warmest on 20 July (negative: "
            "southern hemisphere). A year spans --temperature ± (daily + seasonal)."
        ),
    ] = 0.0,
    wait: Annotated[
        bool,
        typer.Option(
            help="Wait --every seconds between records. --no-wait (with --acquired-at) makes them at once, "
            "their acquisition times still --every seconds apart: a year of records in a minute."
        ),
    ] = True,
    json_lines: JsonLines = False,
) -> None:
    """Post a record every --every seconds, each with a fresh seed, until --count or Ctrl-C.

    A refused record is reported and the stream goes on; the exit code is 1 if any was refused.
    With --temperature, each record's temperature follows the daily and seasonal cycle from its
    acquisition time.
    """
    if not wait and acquired_at is None:
        raise InputError("--no-wait needs --acquired-at: in real time the records would share one time")
    if simulation.temperature is None and (daily_amplitude or seasonal_amplitude):
        raise InputError("--daily-amplitude and --seasonal-amplitude vary a mean: give it with --temperature")
    options = simulation.options(daily_amplitude, seasonal_amplitude)
    stream = streaming.stream(options, fault, k, simulation, start_time(acquired_at), wait)
    stream.check()
    target.check(options.scenario(stream.mode, k))
    # A service manager stops a feed with SIGTERM: stop as cleanly as on Ctrl-C.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    with open_destination(target, simulation.temperature is not None) as destination:
        deliver_stream(stream.plans(), destination, Report(json_lines))


register(app)


def run() -> None:
    """``narxwatch-sim`` (``simulator.client.main``): user errors end with their message, not a traceback.

    Exit code 2 for options that cannot be used (as ``narxwatch``), 1 when the service refuses
    a record or cannot be reached.
    """
    try:
        app()
    except InputError as exc:
        fail(str(exc), EXIT_INPUT_ERROR)
    except ServiceError as exc:
        fail(str(exc), EXIT_SERVICE_ERROR)


def fail(message: str, code: int) -> NoReturn:
    stderr.print("[bold red]error:[/bold red] ", end="")
    stderr.print(message, markup=False)
    raise SystemExit(code)
