"""Where ``narxwatch-sim``'s records go: posted to the service for inspection, or written to files
with a manifest; and how each delivery is printed."""

from __future__ import annotations

import csv
import datetime as dt
import enum
import json
import os
from collections import Counter
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Protocol

import typer
from rich.console import Console
from rich.text import Text

from models.errors import InputError
from recordfiles.channels import MAX_CHANNELS
from recordfiles.writer import UNITS, dump_csv, dump_npz, write_record
from simulator.client.http import API, Service, ServiceError
from simulator.client.scheduler import AnyRecord, AnyScenario, Plan

EXIT_SERVICE_ERROR = 1
DEFAULT_URL = "http://127.0.0.1:8000"
MANIFEST = "manifest.csv"
MANIFEST_COLUMNS = ["path", "fault", "k", "seed"]
TEMPERATURE_COLUMN = "temperature"  # added to the manifest's columns when records have a temperature
STATUS_STYLES = {
    "healthy": "green",
    "faulty": "bold red",
    "unknown_fault": "bold yellow",
    "anomaly": "bold magenta",
}

stdout = Console(soft_wrap=True, highlight=False)
stderr = Console(stderr=True, soft_wrap=True, highlight=False)


class Format(enum.StrEnum):
    json = "json"
    csv = "csv"
    npz = "npz"


MEDIA_TYPES = {Format.csv: "text/csv", Format.npz: "application/x-npz"}


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
        return verdict_text(self.verdict, self.record["id"], describe(plan.describe(), self.record))


def describe(source: str, record: dict[str, Any]) -> str:
    """Where a posted record came from, and whether the service had it already."""
    return f"{source}{'' if record['created'] else ', uploaded before'}"


def verdict_text(verdict: dict[str, Any], record_id: int, source: str) -> Text:
    """One verdict on one line: time, record, status, the mode with k̂, whiteness (or, for a
    healthy baseline's judgement alone, its statistic and severity), and ``source``."""
    line = Text(f"{utc_text(verdict['acquired_at'])}  record {record_id}  ")
    line.append(verdict["status"], style=STATUS_STYLES.get(verdict["status"], ""))
    fields = magnitude_fields(verdict)
    if verdict.get("novelty"):
        fields.append(novelty_field(verdict["novelty"]))
    elif verdict["modes"]:  # a pooled baseline's check alone has none
        fields.append(whiteness_field(verdict))
    if verdict["detected_by"]:
        fields.append("detected by " + ", ".join(verdict["detected_by"]))
    fields.append(f"({source})")
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


def novelty_field(figures: dict[str, Any]) -> str:
    """A healthy baseline's statistic T against its threshold, and the severity (1 when healthy);
    a diverged free run has neither T nor severity."""
    if figures["statistic"] is None:
        return f"free run diverged at sample {figures['diverged_at']}"
    statistic, threshold = figures["statistic"], figures["threshold"]
    sign = ">" if statistic > threshold else "≤"
    return f"T = {statistic:.2f} {sign} {threshold:.2f}  severity {figures['severity']:.3f}"


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


@dataclass(frozen=True)
class Target:
    """Where records go: the options every command takes for it (each field one, named by its
    annotation; ``simulator.client.groups.expanded``)."""

    url: Url = DEFAULT_URL
    key: Key = None
    structure: StructureId = None
    out: OutDir = None
    format: FormatOption = None

    def check(self, scenario: AnyScenario) -> None:
        """Refuse now outputs the structure does not have (naming the channels checks them), and
        posting records of more channels than the service takes."""
        channels = scenario.channels
        if self.out is None and len(channels) > MAX_CHANNELS:
            raise InputError(
                f"these records have {len(channels)} response channels and the service takes at most "
                f"{MAX_CHANNELS}: write them to files with --out DIR, or choose masses with --outputs"
            )


def connect(url: str, key: str | None, otherwise: str = "") -> Service:
    """The service at ``url`` with ``key``, or the key in ``NARXWATCH_SIM_API_KEY_FILE``'s file."""
    key = key or key_from_file()
    if not key:
        raise InputError(
            f"talking to the service needs an API key: pass --key or set NARXWATCH_SIM_API_KEY or {KEY_FILE}"
            + otherwise
        )
    return Service(url, key)


@contextmanager
def open_destination(target: Target, temperature: bool = False) -> Iterator[Destination]:
    """A file writer for ``--out`` (with a manifest column for the records' temperature), else
    the service with the structure to post to."""
    if target.out is not None:
        yield Writer(target.out, target.format or Format.csv, temperature)
        return
    service = connect(target.url, target.key, " (or use --out)")
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
