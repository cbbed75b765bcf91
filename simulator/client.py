"""``narxwatch-sim``: simulated records posted to a running narxwatch service, or written to files.

``narxwatch simulate`` writes one file; this command feeds a service the way a data-acquisition
system would (one record, the paper's four test cases, or a timed stream) and prints each verdict
on one line, so that a demonstration or a smoke test of a deployment needs only a URL and a key.
It reaches the service over HTTP alone, like any other client. The scenario options are those of
``narxwatch simulate``: same names, defaults and messages.

Every record's seed is printed (or written to the manifest), so any record can be made again with
``narxwatch simulate --seed``. Output goes to stdout, one line per record; commentary and errors go
to stderr, so that ``--json`` output stays one JSON document a line.
"""

from __future__ import annotations

import csv
import datetime as dt
import enum
import itertools
import json
import os
import secrets
import signal
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, NoReturn, Protocol

import httpx
import numpy as np
import typer
from rich.console import Console
from rich.text import Text

from models.errors import InputError
from service.channels import MAX_CHANNELS
from simulator import chain
from simulator.chain import ChainRecord, ChainScenario, simulate_chain
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
    parse_assignments,
    parse_colour,
    parse_outputs,
)
from simulator.physics import PhysicalParameters, check_stable
from simulator.recordfile import UNITS, dump_csv, dump_npz, write_record
from simulator.simulate import Effects, Scenario, SimulatedRecord, simulate
from simulator.study import CASES, StudySettings
from simulator.temperature import TemperatureCycle, Thermal

EXIT_SERVICE_ERROR = 1
EXIT_INPUT_ERROR = 2
DEFAULT_URL = "http://127.0.0.1:8000"
API = "/api/v1"
MANIFEST = "manifest.csv"
MANIFEST_COLUMNS = ["path", "fault", "k", "seed"]
TEMPERATURE_COLUMN = "temperature"  # added to the manifest's columns when records have a temperature
SCENARIO_NAMES = [case.name for case in CASES] + ["all", "any"]
STATUS_STYLES = {"healthy": "green", "faulty": "bold red", "unknown_fault": "bold yellow"}
# The option defaults are the study's, so that the paper's cases are simulated as in the paper.
STUDY = StudySettings()

stdout = Console(soft_wrap=True, highlight=False)
stderr = Console(stderr=True, soft_wrap=True, highlight=False)


class ServiceError(Exception):
    """The service refused a request or could not be reached; the message says which and why."""


class Format(enum.StrEnum):
    json = "json"
    csv = "csv"
    npz = "npz"


MEDIA_TYPES = {Format.csv: "text/csv", Format.npz: "application/x-npz"}


# --- Options shared by the subcommands ----------------------------------------------------------

Seed = Annotated[
    int | None,
    typer.Option(min=0, help="Seed of the first record; the next ones use seed + 1, … (default: fresh)."),
]
Url = Annotated[str, typer.Option(envvar="NARXWATCH_SIM_URL", help="Base URL of the narxwatch service.")]
Key = Annotated[
    str | None,
    typer.Option(envvar="NARXWATCH_SIM_API_KEY", show_default=False, help="API key of role ingest or admin."),
]
StructureId = Annotated[
    int | None,
    typer.Option("--structure", min=1, help="Structure id (default: the first one the key can see)."),
]
OutDir = Annotated[
    Path | None,
    typer.Option(
        "--out", help="Write record files and a manifest.csv (path,fault,k,seed) here; post nothing."
    ),
]
FormatOption = Annotated[
    Format | None,
    typer.Option("--format", help="Body to post (default json) or files to write with --out (default csv)."),
]
AcquiredAt = Annotated[
    str | None,
    typer.Option(help="Acquisition time, ISO 8601 with a zone, e.g. 2026-11-21T10:00:00Z (default: now)."),
]
JsonLines = Annotated[bool, typer.Option("--json", help="Print each verdict as one line of JSON.")]


AnyScenario = Scenario | ChainScenario
AnyRecord = SimulatedRecord | ChainRecord


@dataclass(frozen=True)
class ScenarioOptions:
    """The scenario options as given, turned into checked scenarios for any fault and magnitude.

    ``climate`` gives each record its temperature from its acquisition time; ``chain`` the
    n-mass chain's options (the 2-DOF rig without ``--masses``).
    """

    excitation_std: float
    disturbance_std: float
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
        levels = {
            "excitation_std": self.excitation_std,
            "disturbance_std": self.disturbance_std,
            "y_noise_std": self.noise_std,
            "x_noise_std": self.x_noise_std,
            "noise_colour": parse_colour(self.noise_colour),
            "temperature": temperature,
            "thermal": thermal,
        }
        parameters = self.chain.parameters()
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


# --- Where records go: the service, or files ----------------------------------------------------


class Service:
    """The narxwatch REST API over HTTP; every failure becomes a :class:`ServiceError`."""

    def __init__(self, url: str, key: str) -> None:
        if not url.startswith(("http://", "https://")):
            raise InputError(f"--url must start with http:// or https://, got {url!r}")
        self.url = url.rstrip("/")
        try:
            self._http = httpx.Client(
                base_url=self.url, headers={"Authorization": f"Bearer {key}"}, timeout=60
            )
        except httpx.InvalidURL as exc:
            raise InputError(f"--url {url!r} is not a usable URL ({exc})") from None

    def close(self) -> None:
        self._http.close()

    def request(self, method: str, path: str, **options: Any) -> Any:
        try:
            response = self._http.request(method, path, **options)
        except httpx.TransportError as exc:
            reason = str(exc) or type(exc).__name__
            raise ServiceError(
                f"cannot reach narxwatch at {self.url} ({reason}); is the service running there?"
            ) from None
        if response.is_error:
            answer = f"{response.status_code} {response.reason_phrase}"
            raise ServiceError(f"the service answered {answer}: {server_detail(response)}")
        try:
            return response.json()
        except ValueError:
            raise ServiceError(
                f"{self.url} answered {path} without JSON: is it a narxwatch service?"
            ) from None

    def first_structure(self) -> dict[str, Any]:
        structures = self.request("GET", f"{API}/structures")
        if not structures:
            raise ServiceError(
                f"the API key sees no structure at {self.url}: create one (POST {API}/structures with an "
                "admin key) or pass --structure ID"
            )
        return structures[0]


def server_detail(response: httpx.Response) -> str:
    """The service's ``detail`` message: a string, or FastAPI's list of validation errors."""
    try:
        body = response.json()
    except ValueError:
        return "the answer holds no JSON; is the URL that of a narxwatch service?"
    detail = body.get("detail") if isinstance(body, dict) else body
    if isinstance(detail, str):
        return detail
    if isinstance(detail, list) and all(isinstance(item, dict) for item in detail):
        return "; ".join(
            f"{'.'.join(str(part) for part in item.get('loc', []))}: {item.get('msg', item)}"
            for item in detail
        )
    return json.dumps(detail)[:300]


class Delivery(Protocol):
    """What became of one record: a verdict, or a written file."""

    @property
    def label(self) -> str: ...

    def document(self) -> dict[str, Any]: ...

    def text(self, plan: Plan) -> Text: ...


class Destination(Protocol):
    def deliver(self, plan: Plan, record: AnyRecord) -> Delivery: ...


@dataclass(frozen=True)
class Posted:
    """A record stored by the service, with its verdict."""

    record: dict[str, Any]

    @property
    def verdict(self) -> dict[str, Any]:
        return self.record["verdict"]

    @property
    def label(self) -> str:
        mode = self.verdict["fault_mode"]
        return f"faulty {mode}" if mode else self.verdict["status"]

    def document(self) -> dict[str, Any]:
        return self.verdict

    def text(self, plan: Plan) -> Text:
        verdict = self.verdict
        line = Text(f"{utc_text(verdict['acquired_at'])}  record {self.record['id']}  ")
        line.append(verdict["status"], style=STATUS_STYLES.get(verdict["status"], ""))
        fields = [*magnitude_fields(verdict), whiteness_field(verdict)]
        if verdict["detected_by"]:
            fields.append("detected by " + ", ".join(verdict["detected_by"]))
        fields.append(f"({plan.describe()}{'' if self.record['created'] else ', uploaded before'})")
        line.append("  " + "  ".join(fields))
        return line


def magnitude_fields(verdict: dict[str, Any]) -> list[str]:
    """The localised mode (or, for a healthy record, the closest one) with k̂ and its interval."""
    fields = []
    if verdict["fault_mode"]:
        fields.append(f"mode {verdict['fault_mode']}")
    elif verdict["reference_mode"]:
        fields.append(f"closest {verdict['reference_mode']}")
    if verdict["k_hat"] is not None:
        magnitude = f"k̂ = {verdict['k_hat']:.2f} %"
        if verdict["interval"]:
            low, high = verdict["interval"]
            magnitude += f" [{low:.2f}, {high:.2f}]"
        fields.append(magnitude)
    return fields


def whiteness_field(verdict: dict[str, Any]) -> str:
    """Ljung–Box Q of the best-fitting mode against its critical value: why a mode is (not) accepted."""
    best = min(verdict["modes"], key=lambda mode: mode["residual_variance"])
    sign = "<" if best["accepted"] else "≥"
    return f"Q({best['name']}) = {best['q']:.1f} {sign} {best['q_critical']:.1f}"


def utc_text(stamp: str) -> str:
    return dt.datetime.fromisoformat(stamp).astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass(frozen=True)
class Poster:
    """Posts records to one structure with ``inspect=true``."""

    service: Service
    structure_id: int
    format: Format

    def deliver(self, plan: Plan, record: AnyRecord) -> Posted:
        """The body is x and one response y, or the response channels by name (``y1`` … of the
        chain's masses), and the record's temperature as its condition ``temperature`` (in °C, a unit
        NPZ cannot state). A CSV or NPZ of several channels names them with repeated ``y``
        parameters; a structure inspects such records with its vector fault modes."""
        path = f"{API}/structures/{self.structure_id}/records"
        when = plan.acquired_at.isoformat()
        several = len(record.responses) > 1
        y = record.responses if several else next(iter(record.responses.values()))
        named = {"y": list(record.responses)} if several else {}
        conditions = record_conditions(record)
        if self.format is Format.json:
            responses = (
                {"channels": [{"name": name, "y": v.tolist()} for name, v in record.responses.items()]}
                if several
                else {"y": y.tolist()}  # type: ignore[union-attr]
            )
            body = {
                "x": record.x.tolist(),
                **responses,
                "fs": record.fs,
                "acquired_at": when,
                "conditions": [
                    {"name": name, "value": value, "unit": UNITS.get(name)}
                    for name, value in conditions.items()
                ],
            }
            answer = self.service.request("POST", path, params={"inspect": "true"}, json=body)
        else:
            content = (
                dump_csv(record.x, y, record.fs, conditions).encode()
                if self.format is Format.csv
                else dump_npz(record.x, y, record.fs, conditions)
            )
            answer = self.service.request(
                "POST",
                path,
                params={"inspect": "true", "acquired_at": when, **named},
                content=content,
                headers={"Content-Type": MEDIA_TYPES[self.format]},
            )
        if answer.get("verdict") is None:
            raise ServiceError(f"the service stored record {answer.get('id')} but returned no verdict")
        return Posted(answer)


@dataclass(frozen=True)
class Written:
    """A record written to a file and listed in the manifest."""

    path: Path
    row: dict[str, Any]
    label = "written"

    def document(self) -> dict[str, Any]:
        return self.row

    def text(self, plan: Plan) -> Text:
        return Text(f"wrote {self.path}  ({plan.describe()})")


class Writer:
    """Record files numbered on from the manifest already in the directory, so that several runs
    build one set (e.g. experiments for ``narxwatch train fault-mode --experiments manifest.csv``)."""

    def __init__(self, directory: Path, file_format: Format, temperature: bool = False) -> None:
        if file_format is Format.json:
            raise InputError("--out writes record files: use --format csv or npz")
        self.directory = directory
        self.format = file_format
        self.manifest = directory / MANIFEST
        self.columns = MANIFEST_COLUMNS + [TEMPERATURE_COLUMN] * temperature
        self.count = manifest_rows(self.manifest, self.columns)

    def deliver(self, plan: Plan, record: AnyRecord) -> Written:
        self.count += 1
        name = f"record_{self.count:04d}_{plan.scenario.fault}_{plan.scenario.k:g}.{self.format}"
        row = {"path": name, "fault": plan.scenario.fault, "k": plan.scenario.k, "seed": plan.seed}
        conditions = record_conditions(record)
        row |= conditions
        try:
            path = write_record(self.directory / name, record.x, record.responses, record.fs, conditions)
            new = not self.manifest.exists()
            with self.manifest.open("a", newline="") as handle:
                writer = csv.DictWriter(handle, self.columns)
                if new:
                    writer.writeheader()
                writer.writerow(row)
        except OSError as exc:
            raise InputError(f"cannot write into {self.directory} ({exc.strerror})") from None
        return Written(path, row)


def record_conditions(record: AnyRecord) -> dict[str, float]:
    """The operating conditions a record is written or posted with: its temperature, if it has one."""
    return {} if record.temperature is None else {TEMPERATURE_COLUMN: record.temperature}


def manifest_rows(manifest: Path, columns: list[str]) -> int:
    """Rows already in a manifest (0 if there is none); a file of another kind, or a manifest of
    records with (without) a temperature for records without (with) one, is not touched."""
    if not manifest.exists():
        return 0
    try:
        with manifest.open(newline="") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            rows = sum(1 for _ in reader)
    except OSError as exc:
        raise InputError(f"{manifest}: cannot read the manifest ({exc.strerror})") from None
    if header != columns:
        raise InputError(
            f"{manifest} is not a manifest of such records (columns {','.join(columns)}); "
            "choose another --out directory"
        )
    return rows


KEY_FILE = "NARXWATCH_SIM_API_KEY_FILE"


def key_from_file() -> str | None:
    """The key in the file ``NARXWATCH_SIM_API_KEY_FILE`` names: a key handed over in a volume, as
    docker-compose.yml's seed service does, never on a command line or in the environment."""
    path = os.environ.get(KEY_FILE)
    if not path:
        return None
    try:
        return Path(path).read_text().strip() or None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the API key ({exc.strerror})") from None


@dataclass(frozen=True)
class Target:
    """Where records go, as the common options say."""

    url: str
    key: str | None
    structure: int | None
    out: Path | None
    format: Format | None

    def check(self, scenario: AnyScenario) -> None:
        """Refuse now outputs the structure does not have (naming the channels checks them), and
        posting records of more channels than the service takes."""
        channels = scenario.channels
        if self.out is None and len(channels) > MAX_CHANNELS:
            raise InputError(
                f"these records have {len(channels)} response channels and the service takes at most "
                f"{MAX_CHANNELS}: write them to files with --out DIR, or choose masses with --outputs"
            )


@contextmanager
def open_destination(target: Target, temperature: bool = False) -> Iterator[Destination]:
    """A file writer for ``--out`` (with a manifest column for the records' temperature), else
    the service with the structure to post to."""
    if target.out is not None:
        yield Writer(target.out, target.format or Format.csv, temperature)
        return
    key = target.key or key_from_file()
    if not key:
        raise InputError(
            f"posting needs an API key: pass --key or set NARXWATCH_SIM_API_KEY or {KEY_FILE} (or use --out)"
        )
    service = Service(target.url, key)
    try:
        structure_id = target.structure
        if structure_id is None:
            structure = service.first_structure()
            structure_id = structure["id"]
            stderr.print(
                f"posting to structure {structure_id} {structure['name']!r} at {service.url}, the first "
                "this key can see (choose another with --structure)",
                markup=False,
            )
        yield Poster(service, structure_id, target.format or Format.json)
    finally:
        service.close()


# --- Running and reporting ----------------------------------------------------------------------


class Report:
    """Prints each delivery on one line (or as JSON) and counts them per case for the tally."""

    def __init__(self, json_lines: bool) -> None:
        self.json_lines = json_lines
        self.counts: dict[str, Counter[str]] = {}
        self.failures = 0

    def delivered(self, plan: Plan, delivery: Delivery) -> None:
        self.counts.setdefault(plan.case, Counter())[delivery.label] += 1
        if self.json_lines:
            document = delivery.document()
            if plan.scenario.temperature is not None:
                document = {**document, TEMPERATURE_COLUMN: plan.scenario.temperature}
            print(json.dumps(document), flush=True)
        else:
            stdout.print(delivery.text(plan))

    def failed(self, plan: Plan, message: str) -> None:
        self.counts.setdefault(plan.case, Counter())["failed"] += 1
        self.failures += 1
        stderr.print(f"[bold red]failed:[/bold red] {plan.describe()}: ", end="")
        stderr.print(message, markup=False)

    def tally(self) -> None:
        """Counts per case; on stderr with ``--json``, so that stdout stays one verdict a line."""
        console = stderr if self.json_lines else stdout
        for case, counts in self.counts.items():
            listed = ", ".join(f"{label} {count}" for label, count in counts.items())
            total = counts.total()
            console.print(f"{case}: {total} record{'s' * (total != 1)}, {listed}", markup=False)


def deliver_all(plans: Iterable[Plan], destination: Destination, report: Report) -> None:
    """Every record in turn; the first failure ends the run (main turns it into exit code 1)."""
    for plan in plans:
        report.delivered(plan, destination.deliver(plan, plan.simulate()))


def deliver_stream(plans: Iterable[Plan], destination: Destination, report: Report) -> None:
    """Every record in turn, reporting a failed one and going on: a feed outlives a refused record
    or a restarting service. Ctrl-C stops it cleanly; exit code 1 if any record failed."""
    try:
        for plan in plans:
            record = plan.simulate()
            try:
                report.delivered(plan, destination.deliver(plan, record))
            except ServiceError as exc:
                report.failed(plan, str(exc))
    except KeyboardInterrupt:
        stderr.print("stopped")
    finally:
        report.tally()
    if report.failures:
        raise typer.Exit(EXIT_SERVICE_ERROR)


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
def record_command(
    fault: Fault = "none",
    k: Magnitude = 0.0,
    n: Samples = STUDY.inspection_samples,
    seed: Seed = None,
    excitation_std: ExcitationStd = STUDY.excitation_std,
    disturbance_std: DisturbanceStd = STUDY.disturbance_std,
    noise_std: NoiseStd = 0.0,
    x_noise_std: XNoiseStd = 0.0,
    noise_colour: NoiseColour = None,
    effect: EffectList = None,
    param: ParamList = None,
    temperature: Temperature = None,
    thermal_coefficient: ThermalList = None,
    outputs: Outputs = None,
    masses: Masses = None,
    mass: MassValues = None,
    stiffness: StiffnessValues = None,
    damping: DampingValues = None,
    cubic: CubicValues = None,
    response: ResponseOption = None,
    url: Url = DEFAULT_URL,
    key: Key = None,
    structure: StructureId = None,
    out: OutDir = None,
    file_format: FormatOption = None,
    acquired_at: AcquiredAt = None,
    json_lines: JsonLines = False,
) -> None:
    """Simulate one record, post it for inspection and print its verdict."""
    options = ScenarioOptions(
        excitation_std,
        disturbance_std,
        noise_std,
        x_noise_std,
        tuple(effect or ()),
        tuple(param or ()),
        noise_colour,
        None if temperature is None else TemperatureCycle(temperature),
        tuple(thermal_coefficient or ()),
        outputs,
        ChainOptions(masses, mass, stiffness, damping, cubic, response),
    )
    when = start_time(acquired_at) or now()
    plan = Plan("record", options.scenario(fault, k, temperature), n, first_seed(seed), when)
    target = Target(url, key, structure, out, file_format)
    target.check(plan.scenario)
    with open_destination(target, temperature is not None) as destination:
        deliver_all([plan], destination, Report(json_lines))


@app.command("scenario")
def scenario_command(
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
    n: Samples = STUDY.inspection_samples,
    seed: Seed = None,
    excitation_std: ExcitationStd = STUDY.excitation_std,
    disturbance_std: DisturbanceStd = STUDY.disturbance_std,
    noise_std: NoiseStd = 0.0,
    x_noise_std: XNoiseStd = 0.0,
    noise_colour: NoiseColour = None,
    effect: EffectList = None,
    param: ParamList = None,
    temperature: Temperature = None,
    thermal_coefficient: ThermalList = None,
    outputs: Outputs = None,
    masses: Masses = None,
    mass: MassValues = None,
    stiffness: StiffnessValues = None,
    damping: DampingValues = None,
    cubic: CubicValues = None,
    response: ResponseOption = None,
    url: Url = DEFAULT_URL,
    key: Key = None,
    structure: StructureId = None,
    out: OutDir = None,
    file_format: FormatOption = None,
    acquired_at: AcquiredAt = None,
    json_lines: JsonLines = False,
) -> None:
    """Post --runs records of a paper test case (all at one acquisition time) and tally the verdicts."""
    options = ScenarioOptions(
        excitation_std,
        disturbance_std,
        noise_std,
        x_noise_std,
        tuple(effect or ()),
        tuple(param or ()),
        noise_colour,
        None if temperature is None else TemperatureCycle(temperature),
        tuple(thermal_coefficient or ()),
        outputs,
        ChainOptions(masses, mass, stiffness, damping, cubic, response),
    )
    cases = chosen_cases(name, fault, k, options, temperature)
    seeds = itertools.count(first_seed(seed))
    when = start_time(acquired_at) or now()
    plans = [Plan(case, scenario, n, next(seeds), when) for case, scenario in cases for _ in range(runs)]
    report = Report(json_lines)
    target = Target(url, key, structure, out, file_format)
    for _, scenario in cases:
        target.check(scenario)
    with open_destination(target, temperature is not None) as destination:
        deliver_all(plans, destination, report)
    report.tally()


@app.command("stream")
def stream_command(
    every: Annotated[float, typer.Option(min=0, help="Seconds between records.")] = 5.0,
    count: Annotated[int | None, typer.Option(min=1, help="Records to send (default: until Ctrl-C).")] = None,
    drift: Annotated[
        float,
        typer.Option(help="Growth of k per record [%]; grows the --fault mode, or k2 if there is none."),
    ] = 0.0,
    scenario: Annotated[
        Course | None,
        typer.Option(
            help="How the fault develops in acquisition time: healthy (none), step (--k from --onset), "
            "drift (--rate % a day from --onset), intermittent (--k in a --duty share of the records "
            "from --onset). Default: --fault at --k growing by --drift a record."
        ),
    ] = None,
    onset: Annotated[
        float, typer.Option(help="Days of acquisition time after the first record when the fault begins.")
    ] = 0.0,
    rate: Annotated[float, typer.Option(help="Growth of k for --scenario drift [% a day].")] = 0.0,
    duty: Annotated[
        float, typer.Option(help="Share of records showing the fault for --scenario intermittent.")
    ] = 0.5,
    per_day: Annotated[
        float | None,
        typer.Option(
            help="Records per day of acquisition time: stamps 24 h / PER_DAY apart, whatever --every "
            "(default: --every seconds apart)."
        ),
    ] = None,
    fault: Fault = "none",
    k: Magnitude = 0.0,
    n: Samples = STUDY.inspection_samples,
    seed: Seed = None,
    excitation_std: ExcitationStd = STUDY.excitation_std,
    disturbance_std: DisturbanceStd = STUDY.disturbance_std,
    noise_std: NoiseStd = 0.0,
    x_noise_std: XNoiseStd = 0.0,
    noise_colour: NoiseColour = None,
    effect: EffectList = None,
    param: ParamList = None,
    temperature: Temperature = None,
    thermal_coefficient: ThermalList = None,
    outputs: Outputs = None,
    masses: Masses = None,
    mass: MassValues = None,
    stiffness: StiffnessValues = None,
    damping: DampingValues = None,
    cubic: CubicValues = None,
    response: ResponseOption = None,
    url: Url = DEFAULT_URL,
    key: Key = None,
    structure: StructureId = None,
    out: OutDir = None,
    file_format: FormatOption = None,
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
    if temperature is None and (daily_amplitude or seasonal_amplitude):
        raise InputError("--daily-amplitude and --seasonal-amplitude vary a mean: give it with --temperature")
    options = ScenarioOptions(
        excitation_std,
        disturbance_std,
        noise_std,
        x_noise_std,
        tuple(effect or ()),
        tuple(param or ()),
        noise_colour,
        None if temperature is None else TemperatureCycle(temperature, daily_amplitude, seasonal_amplitude),
        tuple(thermal_coefficient or ()),
        outputs,
        ChainOptions(masses, mass, stiffness, damping, cubic, response),
    )
    stream = Stream(
        options,
        fault,
        k,
        drift,
        n,
        first_seed(seed),
        every,
        count,
        start_time(acquired_at),
        scenario,
        onset,
        rate,
        duty,
        per_day,
        wait,
    )
    stream.check()
    target = Target(url, key, structure, out, file_format)
    target.check(options.scenario(stream.mode, k))
    # A service manager stops a feed with SIGTERM: stop as cleanly as on Ctrl-C.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    with open_destination(target, temperature is not None) as destination:
        deliver_stream(stream.plans(), destination, Report(json_lines))


def main() -> None:
    """Console-script entry point: user errors end with their message, not a traceback.

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
