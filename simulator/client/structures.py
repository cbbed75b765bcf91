"""``narxwatch-sim``'s commands for a structure of one's own: create it, upload its record files,
train its models from them and read its verdicts, over the same HTTP client, options and errors as
the simulated feeds (:mod:`~simulator.client.destinations`).

Each command prints what the service made, one line each; ``--quiet`` prints only the ids, in the
form the next command takes them (``--structure ID``, ``--records 1,2,3``), so that a shell script
can carry them on.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from models.errors import InputError
from recordfiles.quantities import QUANTITIES, UNIT_HELP, Quantity, SignalDeclaration, signal_label
from simulator.client.destinations import (
    DEFAULT_URL,
    Key,
    Url,
    connect,
    describe,
    stderr,
    stdout,
    verdict_text,
)
from simulator.client.groups import expanded
from simulator.client.http import API, Service, ServiceError

# The media type each record file is sent as, by its suffix (the service's own names for them).
MEDIA_TYPES = {
    ".csv": "text/csv",
    ".json": "application/json",
    ".npz": "application/x-npz",
    ".mat": "application/x-matlab-data",
}

Structure = Annotated[int, typer.Option("--structure", min=1, help="Structure id.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="Print only the ids, for the next command.")]


def id_list(text: str) -> list[int]:
    """``1,2,3`` as ids, as ``upload --quiet`` prints them."""
    try:
        ids = [int(part) for part in text.replace(",", " ").split()]
    except ValueError:
        raise InputError(
            f"--records takes record ids separated by commas, e.g. 1,2,3; got {text!r}"
        ) from None
    if not ids:
        raise InputError("--records names no record")
    return ids


def number_list(text: str) -> list[float]:
    try:
        return [float(part) for part in text.replace(",", " ").split()]
    except ValueError:
        raise InputError(
            f"--k takes magnitudes in percent separated by commas, e.g. -8,0,8; got {text!r}"
        ) from None


class Signal(StrEnum):
    """A signal a structure declares what it measures: x (the excitation) or y (the response)."""

    excitation = "excitation"
    response = "response"


Records = Annotated[str, typer.Option("--records", help="Record ids, separated by commas: 1,2,3.")]
Excitation = Annotated[
    Quantity | None,
    typer.Option(
        "--excitation",
        help=f"What x measures: {', '.join(QUANTITIES)}. Not given: not declared by create, kept by update.",
    ),
]
Response = Annotated[
    Quantity | None,
    typer.Option(
        "--response",
        help="What y (every response channel) measures, as --excitation.",
    ),
]
ExcitationUnit = Annotated[str | None, typer.Option(help=f"The unit of x, {UNIT_HELP}; with --excitation.")]
ResponseUnit = Annotated[str | None, typer.Option(help=f"The unit of y, {UNIT_HELP}; with --response.")]


def declaration(signal: str, quantity: str | None, unit: str | None) -> dict[str, Any]:
    """The body's declaration of ``signal`` (excitation or response), none when not given; its
    unit is checked by the service, by the same rule as everywhere."""
    if quantity is None:
        if unit is not None:
            raise InputError(
                f"--{signal}-unit needs --{signal}: say what the signal measures, e.g. --{signal} force"
            )
        return {}
    return {signal: {"quantity": quantity, "unit": unit}}


def declared(structure: dict[str, Any]) -> str:
    """What a structure says its x and y are, as ", force x [N], acceleration y [m/s²]"; nothing
    where it declares neither."""
    signals = [
        signal_label(symbol, SignalDeclaration(**structure[key]) if structure.get(key) else None)
        for symbol, key in (("x", "excitation"), ("y", "response"))
    ]
    return "" if signals == ["x", "y"] else ", " + ", ".join(signals)


def described(structure: dict[str, Any]) -> str:
    """A structure as its commands print it: id, name, sampling rate and declarations."""
    return (
        f"structure {structure['id']} {structure['name']!r}, fs = {structure['fs']:g} Hz{declared(structure)}"
    )


# How often a queued training's job is asked after, and how often a progress line says it still runs.
POLL_SECONDS, PROGRESS_SECONDS = 2.0, 30.0
Wait = Annotated[
    bool,
    typer.Option(
        "--wait",
        help="If the training is queued as a job (a large one), follow the job to its end and print the "
        "version it made; exit 1 with the job's error if it fails.",
    ),
]
WaitSeconds = Annotated[
    float,
    typer.Option(min=1, help="With --wait, how long to wait [s] before giving up (the job goes on)."),
]
WAIT_SECONDS = 3600.0

Terms = Annotated[
    str | None,
    typer.Option(
        help="Model terms separated by commas (default: a baseline's are chosen for the structure from its "
        "records; a fault mode's are the active baseline's)."
    ),
]


@contextmanager
def service(url: str, key: str | None) -> Iterator[Service]:
    client = connect(url, key)
    try:
        yield client
    finally:
        client.close()


structures_app = typer.Typer(
    help="Create, change and list structures (an admin key creates and changes them).",
    no_args_is_help=True,
    rich_markup_mode=None,
)
train_app = typer.Typer(
    help="Train a structure's models from its stored records (admin key).",
    no_args_is_help=True,
    rich_markup_mode=None,
)


@dataclass(frozen=True)
class Declarations:
    """What x and y measure, as ``structures create`` and ``update`` take them (each field an
    option; :func:`~simulator.client.groups.expanded`)."""

    excitation: Excitation = None
    excitation_unit: ExcitationUnit = None
    response: Response = None
    response_unit: ResponseUnit = None

    def body(self) -> dict[str, Any]:
        """The declarations given, as the service's body takes them."""
        return {
            **declaration("excitation", self.excitation, self.excitation_unit),
            **declaration("response", self.response, self.response_unit),
        }


@structures_app.command("create")
@expanded
def create_structure(
    *,
    name: Annotated[str, typer.Option(help="The structure's name.")],
    fs: Annotated[float, typer.Option(help="Sampling rate [Hz] every record of it must have.")],
    description: Annotated[str, typer.Option(help="Free text.")] = "",
    signals: Declarations,
    url: Url = DEFAULT_URL,
    key: Key = None,
    quiet: Quiet = False,
) -> None:
    """Create a structure and print its id; --excitation and --response declare what x and y
    measure, for the dashboard's charts."""
    body = {"name": name, "fs": fs, "description": description, **signals.body()}
    with service(url, key) as client:
        made = client.request("POST", f"{API}/structures", json=body)
    stdout.print(made["id"] if quiet else described(made), markup=False)


@structures_app.command("update")
@expanded
def update_structure(
    *,
    structure: Structure,
    name: Annotated[str | None, typer.Option(help="Its new name.")] = None,
    description: Annotated[str | None, typer.Option(help="Its new description.")] = None,
    signals: Declarations,
    withdraw: Annotated[
        list[Signal] | None,
        typer.Option(
            help="Withdraw what x (excitation) or y (response) was declared to measure (repeatable)."
        ),
    ] = None,
    url: Url = DEFAULT_URL,
    key: Key = None,
    quiet: Quiet = False,
) -> None:
    """Change a structure's name, description or what x and y measure; what is not given stays.
    Once it has records, a declaration can only be completed (given where there was none, or its
    unit where none was stated): the service refuses to change or withdraw it, saying why."""
    given = {"name": name, "description": description}
    body = {field: value for field, value in given.items() if value is not None} | signals.body()
    for signal in withdraw or []:
        if signal.value in body:
            raise InputError(f"--{signal.value} and --withdraw {signal.value}: give one or the other")
        body[signal.value] = None
    if not body:
        raise InputError(
            "nothing to change: give --name, --description, --excitation, --response or --withdraw"
        )
    with service(url, key) as client:
        changed = client.request("PATCH", f"{API}/structures/{structure}", json=body)
    stdout.print(changed["id"] if quiet else described(changed), markup=False)


@structures_app.command("list")
def list_structures(url: Url = DEFAULT_URL, key: Key = None) -> None:
    """The structures the key can see, each with its latest status."""
    with service(url, key) as client:
        listed = [structure for page in client.pages(f"{API}/structures") for structure in page]
    for structure in listed:
        status = structure["status"] or "no verdict yet"
        stdout.print(f"{described(structure)}, {status}", markup=False)


def upload_command(
    files: Annotated[list[Path], typer.Argument(help="Record files: .csv, .json, .npz or .mat.")],
    structure: Structure,
    inspect: Annotated[bool, typer.Option(help="Inspect each record and print its verdict.")] = False,
    url: Url = DEFAULT_URL,
    key: Key = None,
    quiet: Quiet = False,
) -> None:
    """Upload record files to a structure, print each record's id (and, with --inspect, its verdict).

    --quiet prints only the ids, separated by commas, as --records takes them.
    """
    bodies = [(path, read_body(path)) for path in files]  # every file readable before any is sent
    ids = []
    with service(url, key) as client:
        for path, (content, media_type) in bodies:
            record = client.request(
                "POST",
                f"{API}/structures/{structure}/records",
                params={"inspect": "true"} if inspect else {},
                content=content,
                headers={"Content-Type": media_type},
            )
            ids.append(record["id"])
            if quiet:
                continue
            if inspect:
                stdout.print(verdict_text(record["verdict"], record["id"], describe(str(path), record)))
            else:
                stdout.print(f"record {record['id']}  ({describe(str(path), record)})", markup=False)
    if quiet:
        stdout.print(",".join(str(record_id) for record_id in ids), markup=False)


def read_body(path: Path) -> tuple[bytes, str]:
    media_type = MEDIA_TYPES.get(path.suffix.lower())
    if media_type is None:
        raise InputError(f"{path}: send a record file ending in {', '.join(MEDIA_TYPES)}")
    try:
        return path.read_bytes(), media_type
    except OSError as exc:
        raise InputError(f"{path}: cannot read it ({exc.strerror})") from None


def trained(answer: dict[str, Any]) -> None:
    """A model version made, or a training queued as a job (a large one) when not waited for."""
    if "job_id" in answer:
        stdout.print(f"{answer['detail']}: job {answer['job_id']}, {answer['location']}", markup=False)
        return
    model = "baseline" if answer["kind"] == "baseline" else f"fault mode {answer['name']}"
    stdout.print(
        f"{model} version {answer['version']} (model {answer['id']}), "
        f"{len(answer['terms'])} terms, {'active' if answer['active'] else 'inactive'}",
        markup=False,
    )
    choice = answer["training"].get("choice")
    if choice:
        stdout.print(f"  terms chosen for the structure: {', '.join(choice['terms'])}", markup=False)
    novelty = (answer["statistics"] or {}).get("novelty")
    if novelty:
        judges = (
            "judges records alone"
            if novelty["judges_records"]
            else f"cannot judge records alone: {novelty['reason']}"
        )
        stdout.print(f"  {judges}", markup=False)


def followed(client: Service, answer: dict[str, Any], structure: int, seconds: float) -> dict[str, Any]:
    """The version a training made: the answer itself, or, for a training queued as a job, the
    version the job names once done."""
    if "job_id" not in answer:
        return answer
    job = finished_job(client, answer, seconds)
    if job.get("model") is None:
        raise ServiceError(f"job {job['id']} is done but names no model version: is the service older?")
    models = client.request("GET", f"{API}/structures/{structure}/models")
    return next(model for model in models if model["id"] == job["model"]["id"])


def finished_job(client: Service, queued: dict[str, Any], seconds: float) -> dict[str, Any]:
    """The job of a 202 answer (``queued``) once done, asked after every :data:`POLL_SECONDS`, a
    progress line on stderr at each change of state and every :data:`PROGRESS_SECONDS`. A failed
    job, or one not ended within ``seconds``, is a :class:`ServiceError` saying so."""
    job_id, start, said = queued["job_id"], time.monotonic(), None
    stderr.print(f"{queued['detail']}: job {job_id}; waiting for it up to {seconds:g} s", markup=False)
    while True:
        job = client.request("GET", queued["location"])
        elapsed = time.monotonic() - start
        if job["state"] == "done":
            return job
        if job["state"] == "failed":
            raise ServiceError(f"the training's job {job_id} failed: {job['error']}")
        if elapsed >= seconds:
            raise ServiceError(
                f"job {job_id} is still {job['state']} after {seconds:g} s; it goes on in the service: "
                f"follow it at {queued['location']}"
            )
        if (job["state"], elapsed // PROGRESS_SECONDS) != said:
            said = (job["state"], elapsed // PROGRESS_SECONDS)
            stderr.print(f"job {job_id} {job['state']}, {elapsed:.0f} s", markup=False)
        time.sleep(min(POLL_SECONDS, seconds - elapsed))


@dataclass(frozen=True)
class Training:
    """How ``train baseline`` and ``train fault-mode`` send a training and follow it, as given
    (each field an option; :func:`~simulator.client.groups.expanded`)."""

    terms: Terms = None
    wait: Wait = False
    wait_seconds: WaitSeconds = WAIT_SECONDS
    url: Url = DEFAULT_URL
    key: Key = None

    def train(self, structure: int, kind: str, body: dict[str, Any]) -> None:
        """Post ``body`` (the terms given added) to the structure's ``models/<kind>``, follow a
        queued training to its end if asked to, and print the version made."""
        if self.terms is not None:
            body = body | {"terms": [term.strip() for term in self.terms.split(",") if term.strip()]}
        with service(self.url, self.key) as client:
            answer = client.request("POST", f"{API}/structures/{structure}/models/{kind}", json=body)
            trained(followed(client, answer, structure, self.wait_seconds) if self.wait else answer)


@train_app.command("baseline")
@expanded
def train_baseline(*, structure: Structure, records: Records, training: Training) -> None:
    """Identify the healthy structure's NARX from its stored healthy records."""
    training.train(structure, "baseline", {"record_ids": id_list(records)})


@train_app.command("fault-mode")
@expanded
def train_fault_mode(
    *,
    structure: Structure,
    name: Annotated[str, typer.Option(help="Fault-mode name, e.g. k2.")],
    records: Records,
    k: Annotated[
        str, typer.Option("--k", help="Each record's fault magnitude [%], in the order of --records.")
    ],
    training: Training,
) -> None:
    """Identify a fault mode as a functional NARX from stored records at known magnitudes; it
    becomes the mode records are inspected with, over the range of --k."""
    ids, magnitudes = id_list(records), number_list(k)
    if len(ids) != len(magnitudes):
        raise InputError(
            f"--records names {len(ids)} records and --k {len(magnitudes)} magnitudes: give one each"
        )
    body = {
        "name": name,
        "k_min": min(magnitudes),
        "k_max": max(magnitudes),
        "experiments": [{"record_id": i, "k": value} for i, value in zip(ids, magnitudes, strict=True)],
    }
    training.train(structure, "fault-modes", body)


def verdicts_command(
    structure: Structure,
    limit: Annotated[int, typer.Option(min=1, max=1000, help="How many, the latest first.")] = 20,
    json_lines: Annotated[
        bool, typer.Option("--json", help="Print each verdict as one line of JSON.")
    ] = False,
    url: Url = DEFAULT_URL,
    key: Key = None,
) -> None:
    """A structure's latest verdicts, the latest first."""
    with service(url, key) as client:
        page = client.request("GET", f"{API}/structures/{structure}/verdicts", params={"limit": limit})
    for verdict in page["items"]:
        if json_lines:
            print(json.dumps(verdict), flush=True)
        else:
            stdout.print(verdict_text(verdict, verdict["record_id"], f"verdict {verdict['id']}"))


def register(app: typer.Typer) -> None:
    """Add these commands to ``narxwatch-sim``."""
    app.add_typer(structures_app, name="structures")
    app.command("upload")(upload_command)
    app.add_typer(train_app, name="train")
    app.command("verdicts")(verdicts_command)
