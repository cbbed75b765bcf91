"""``narxwatch-sim`` run as a user runs it (the installed console script, the key in the
environment) against the real service over HTTP, on SQLite and on PostgreSQL. A record, a scenario
and a stream posted, Ctrl-C and a training waited for run the script as a process, each once;
the other records and streams, the trainings given up on or failed, the refusals, the files
written and the structure commands go through its entry point in this process (``invoke_sim``),
the same code but for the second of imports a new process spends.

The structure is trained through the API from 5 magnitudes per fault mode: coarser than the
paper's 17, enough for the obvious cases used here (k2 29 %, k1 30 %). Seeds are fixed so that
every run posts the same records.
"""

from __future__ import annotations

import datetime as dt
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select

from harness.api_helpers import RIG_TERMS, simulated, upload_simulated, wait_for
from harness.cli import invoke
from harness.job_helpers import run_jobs
from harness.live import LiveServer, Tenant, free_port
from recordfiles.reader import read_record
from service.cli.modelfiles import read_manifest
from service.config import Settings
from service.domain import fleet, retention
from service.security import Role
from service.tables import Organisation
from simulator.simulate import Scenario, simulate
from simulator.study import StudySettings
from simulator.temperature import TemperatureCycle

SIM = shutil.which("narxwatch-sim", path=str(Path(sys.executable).parent))
SETTINGS = StudySettings()
MAGNITUDES = [-32.0, -16.0, 0.0, 16.0, 32.0]
VERDICT_LINE = re.compile(
    r"^(?P<when>\S+)  record (?P<record>\d+)  (?P<status>healthy|faulty|unknown_fault)  (?P<rest>.*)$"
)


@dataclass
class Trained:
    server: LiveServer
    tenant: Tenant
    structure_id: int
    key: str  # an ingest key of the tenant, as a user would export it


def run_sim(
    *args: str, key: str | None = None, url: str | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    assert SIM, "the narxwatch-sim console script is not installed next to this Python"
    return subprocess.run(
        [SIM, *args], env=sim_env(key, url), cwd=cwd, capture_output=True, text=True, timeout=120
    )


def invoke_sim(
    *args: str, key: str | None = None, url: str | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """:func:`run_sim` through the console script's entry point in this process: what the command
    says and its exit code where the process is not what is tested (``post`` and the streams run
    it as a process)."""
    return invoke(
        *args, cwd=cwd or Path.cwd(), check=False, script="narxwatch-sim", environ=sim_env(key, url)
    )


def sim_env(key: str | None, url: str | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_SIM_")}
    if key is not None:
        env["NARXWATCH_SIM_API_KEY"] = key
    if url is not None:
        env["NARXWATCH_SIM_URL"] = url
    return env


def upload_npz(client, structure_id: int, record) -> int:
    buffer = io.BytesIO()
    np.savez(buffer, x=record.x, y=record.y, fs=record.fs)
    response = client.post(
        f"/api/v1/structures/{structure_id}/records",
        content=buffer.getvalue(),
        headers={"Content-Type": "application/x-npz"},
    )
    assert response.status_code == 201, response.text
    return response.json()["id"]


def verdicts(trained: Trained, **params: str) -> list[dict]:
    response = trained.tenant.viewer.get(
        f"/api/v1/structures/{trained.structure_id}/verdicts", params={"limit": 1000, **params}
    )
    assert response.status_code == 200 and response.json()["next_cursor"] is None, response.text
    return response.json()["items"]


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    """The client sees only HTTP: the database behind the app is the API tests' concern, on both
    backends (tests/test_api_*.py), so these run against SQLite's server alone."""
    return sqlite_api_server


@pytest.fixture(scope="module")
def trained(api_server: LiveServer):  # yields Trained
    """A structure with k2 and k1 fault-mode models trained through the API."""
    tenant = Tenant.create(api_server)
    response = tenant.admin.post("/api/v1/structures", json={"name": "rig", "fs": 1500.0})
    assert response.status_code == 201, response.text
    structure_id = response.json()["id"]
    seeds = iter(np.random.SeedSequence(7).spawn(2 * len(MAGNITUDES)))
    for mode in ("k2", "k1"):
        experiments = []
        for k in MAGNITUDES:
            record = simulate(SETTINGS.scenario(mode, k), 2000, next(seeds))
            experiments.append({"record_id": upload_npz(tenant.ingest, structure_id, record), "k": k})
        body = {"name": mode, "k_min": -32.0, "k_max": 32.0, "experiments": experiments, "terms": RIG_TERMS}
        response = tenant.admin.post(f"/api/v1/structures/{structure_id}/models/fault-modes", json=body)
        assert response.status_code == 201, response.text
    yield Trained(api_server, tenant, structure_id, api_server.key(Role.ingest, tenant.name))
    for client in (tenant.admin, tenant.ingest, tenant.viewer):
        client.close()


def post(
    trained: Trained, *args: str, run: Callable[..., Any] = invoke_sim
) -> subprocess.CompletedProcess[str]:
    """Run against the trained structure, in this process (``run=run_sim``: as a process); the run
    must succeed."""
    result = run(*args, "--structure", str(trained.structure_id), key=trained.key, url=trained.server.url)
    assert result.returncode == 0, result.stderr
    assert trained.key not in result.stdout + result.stderr
    return result


def test_record_prints_the_verdict_the_service_stored(trained: Trained):
    result = post(
        trained,
        "record",
        "--fault",
        "k2",
        "--k",
        "29",
        "--seed",
        "11",
        "--acquired-at",
        "2026-11-21T10:00:00Z",
        run=run_sim,
    )
    lines = result.stdout.splitlines()
    assert len(lines) == 1
    line = VERDICT_LINE.match(lines[0])
    assert line, lines[0]
    assert line["when"] == "2026-11-21T10:00:00Z" and line["status"] == "faulty"
    k_hat, low, high = map(float, re.search(r"k̂ = (\S+) % \[(\S+), (\S+)\]", line["rest"]).groups())
    assert abs(k_hat - 29) < 1 and low < k_hat < high
    assert "mode k2" in line["rest"] and "detected by k2" in line["rest"] and "seed 11" in line["rest"]
    stored = next(v for v in verdicts(trained) if v["record_id"] == int(line["record"]))
    assert (stored["status"], stored["fault_mode"]) == ("faulty", "k2")
    assert f"k̂ = {stored['k_hat']:.2f} %" in line["rest"]


def test_record_json_over_npz_is_the_stored_verdict(trained: Trained):
    result = post(
        trained, "record", "--fault", "k1", "--k", "30", "--seed", "12", "--format", "npz", "--json"
    )
    (line,) = result.stdout.splitlines()
    verdict = json.loads(line)
    assert (verdict["status"], verdict["fault_mode"]) == ("faulty", "k1")
    assert verdict == trained.tenant.viewer.get(f"/api/v1/verdicts/{verdict['id']}").json()


def test_scenario_iv_prints_a_line_per_run_and_a_tally(trained: Trained):
    before = len(verdicts(trained))
    result = post(trained, "scenario", "IV", "--runs", "2", "--seed", "21")
    *lines, tally = result.stdout.splitlines()
    assert len(lines) == 2 and all(VERDICT_LINE.match(line) for line in lines)
    assert "(simulated k1 30 %, seed 21)" in lines[0] and "(simulated k1 30 %, seed 22)" in lines[1]
    assert tally == "case IV (k1 fault, 30 % reduction): 2 records, faulty k1 2"
    assert len(verdicts(trained)) == before + 2


def test_stream_posts_count_records_every_period(trained: Trained):
    before = len(verdicts(trained))
    start = "2024-01-01T00:00:00+00:00"
    args = ["stream", "--every", "0.2", "--count", "3", "--acquired-at", start, "--format", "csv"]
    result = post(trained, *args, run=run_sim)
    *lines, tally = result.stdout.splitlines()
    assert len(lines) == 3 and all(VERDICT_LINE.match(line) for line in lines)
    assert tally.startswith("stream: 3 records, ")
    assert len(verdicts(trained)) == before + 3
    streamed = verdicts(trained, start=start, end="2024-01-01T00:00:01+00:00")
    offsets = sorted(
        dt.datetime.fromisoformat(v["acquired_at"]) - dt.datetime.fromisoformat(start) for v in streamed
    )
    assert offsets == [dt.timedelta(seconds=s) for s in (0.0, 0.2, 0.4)]
    seeds = [int(re.search(r"seed (\d+)\)", line)[1]) for line in lines]
    assert seeds == [seeds[0], seeds[0] + 1, seeds[0] + 2]


@pytest.mark.parametrize(("body", "unit"), [("json", "°C"), ("csv", "°C"), ("npz", None)])
def test_a_streamed_records_temperature_is_stored_as_its_condition(trained: Trained, body: str, unit):
    """Each record of a stream over the seasons arrives with the temperature it was simulated at,
    to the last digit, as the condition ``temperature`` of its stored record and verdict (an NPZ
    body states no unit)."""
    start = dt.datetime(2025, 1, 1, 3, tzinfo=dt.UTC)
    every = 91 * 86400 + 6 * 3600
    args = ["stream", "--temperature", "10", "--daily-amplitude", "5", "--seasonal-amplitude", "15"]
    args += ["--every", str(every), "--count", "2", "--no-wait", "--acquired-at", start.isoformat()]
    result = post(trained, *args, "--format", body, "--json")
    cycle = TemperatureCycle(10.0, 5.0, 15.0)
    expected = [cycle.at(start + dt.timedelta(seconds=i * every)) for i in range(2)]
    printed = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["temperature"] for line in printed] == expected
    stored = {v["id"]: v for v in verdicts(trained)}
    for line, temperature in zip(printed, expected, strict=True):
        condition = {"name": "temperature", "value": temperature, "unit": unit}
        assert stored[line["id"]]["conditions"] == line["conditions"] == [condition]


def test_out_writes_files_and_a_manifest_and_posts_nothing(trained: Trained, tmp_path: Path):
    before = len(verdicts(trained))
    args = ["stream", "--every", "0", "--count", "3", "--fault", "k2", "--k", "-20", "--drift", "20"]
    result = post(trained, *args, "--seed", "31", "--out", str(tmp_path))
    assert len(verdicts(trained)) == before
    names = ["record_0001_k2_-20.csv", "record_0002_k2_0.csv", "record_0003_k2_20.csv"]
    *lines, tally = result.stdout.splitlines()
    assert [line.split()[1] for line in lines] == [str(tmp_path / n) for n in names]
    assert tally == "stream: 3 records, written 3"
    rows = (tmp_path / "manifest.csv").read_text().splitlines()
    assert rows == ["path,fault,k,seed"] + [
        f"{n},k2,{k},{s}" for n, k, s in zip(names, (-20.0, 0.0, 20.0), (31, 32, 33), strict=True)
    ]
    # The manifest is the one `narxwatch train fault-mode --experiments` reads, and its seeds
    # make each record again.
    assert read_manifest(tmp_path / "manifest.csv") == [
        (tmp_path / n, k) for n, k in zip(names, (-20.0, 0.0, 20.0), strict=True)
    ]
    again = simulate(Scenario(fault="k2", k=20.0, disturbance_std=SETTINGS.disturbance_std), 2000, 33)
    np.testing.assert_array_equal(read_record(tmp_path / names[2]).y, again.y)


def test_out_numbers_on_from_an_existing_manifest(tmp_path: Path):
    for fault, k in (("none", "0"), ("k1", "12.5")):
        result = invoke_sim(
            "record", "--fault", fault, "--k", k, "--seed", "5", "--format", "npz", "--out", str(tmp_path)
        )
        assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "manifest.csv",
        "record_0001_none_0.npz",
        "record_0002_k1_12.5.npz",
    ]
    assert (tmp_path / "manifest.csv").read_text().splitlines()[1:] == [
        "record_0001_none_0.npz,none,0.0,5",
        "record_0002_k1_12.5.npz,k1,12.5,5",
    ]


@pytest.mark.parametrize(
    ("role", "message"),
    [
        (None, "401 Unauthorized: the API key is not valid"),
        (Role.viewer, "403 Forbidden: this needs a key of role 'ingest' or higher"),
    ],
    ids=["unknown key", "viewer key"],
)
def test_a_refused_key_exits_1_with_the_service_message(trained: Trained, role, message):
    key = (
        f"nw_{uuid.uuid4().hex[:12]}_not-a-key"
        if role is None
        else trained.server.key(role, trained.tenant.name)
    )
    result = invoke_sim("record", "--seed", "1", key=key, url=trained.server.url)
    assert result.returncode == 1
    assert message in result.stderr and "Traceback" not in result.stderr
    assert key not in result.stdout + result.stderr and result.stdout == ""


def test_an_unreachable_service_exits_1_naming_the_url():
    url = f"http://127.0.0.1:{free_port()}"
    result = invoke_sim("record", "--seed", "1", key="nw_x_y", url=url)
    assert result.returncode == 1
    assert f"cannot reach narxwatch at {url}" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["record", "--effect", "gremlins=3"], "cannot read effect 'gremlins=3'"),
        (["record", "--param", "c1=0", "--param", "c2=0"], "unstable"),
        (["record", "--acquired-at", "2026-11-21T10:00:00"], "needs a timezone"),
        (["stream", "--count", "101", "--fault", "k2", "--drift", "1"], "would remove the spring entirely"),
        (["scenario", "IV", "--fault", "k2"], "use 'any' for --fault and --k"),
        (["record", "--out", "files", "--format", "json"], "use --format csv or npz"),
    ],
    ids=["effect", "unstable", "naive time", "drift", "case with fault", "json files"],
)
def test_unusable_options_exit_2_before_contacting_the_service(args, message, tmp_path: Path):
    # Nothing listens at this URL: exit code 2, not 1, shows the options were refused first.
    result = invoke_sim(*args, key="nw_x_y", url=f"http://127.0.0.1:{free_port()}", cwd=tmp_path)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_default_structure_is_the_first_the_key_sees(trained: Trained):
    spare = trained.tenant.admin.post(
        "/api/v1/structures", json={"name": f"spare-{uuid.uuid4().hex[:8]}", "fs": 1500.0}
    )
    assert spare.status_code == 201 and spare.json()["id"] > trained.structure_id
    result = invoke_sim("record", "--seed", "41", "--json", key=trained.key, url=trained.server.url)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["structure_id"] == trained.structure_id
    assert f"posting to structure {trained.structure_id} 'rig'" in result.stderr


def test_a_key_without_structures_is_told_so(api_server: LiveServer, tenant: Tenant):
    key = api_server.key(Role.ingest, tenant.name)
    result = invoke_sim("record", "--seed", "1", key=key, url=api_server.url)
    assert result.returncode == 1
    assert "the API key sees no structure" in result.stderr and "--structure ID" in result.stderr


def test_stream_reports_a_refused_record_and_goes_on(api_server: LiveServer, tenant: Tenant):
    untrained = tenant.admin.post("/api/v1/structures", json={"name": "new", "fs": 1500.0}).json()["id"]
    key = api_server.key(Role.ingest, tenant.name)
    result = invoke_sim(
        "stream", "--every", "0", "--count", "2", "--structure", str(untrained), key=key, url=api_server.url
    )
    assert result.returncode == 1
    failures = [line for line in result.stderr.splitlines() if line.startswith("failed: ")]
    assert len(failures) == 2 and all("has no active fault-mode model" in line for line in failures)
    assert result.stdout.splitlines() == ["stream: 2 records, failed 2"]


def test_ctrl_c_stops_a_stream_cleanly(trained: Trained):
    args = [SIM, "stream", "--every", "60", "--structure", str(trained.structure_id)]
    forking = _signal_state("thread-self")  # what the child inherits: this thread's mask
    with subprocess.Popen(
        args,
        env=sim_env(trained.key, trained.server.url),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # As from a terminal: a pytest started in the background of a shell without job control
        # ignores SIGINT, and a child inherits that, which Python then leaves alone.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    ) as process:
        first = process.stdout.readline()  # the first record is posted at once, the next in a minute
        process.send_signal(signal.SIGINT)
        try:
            out, err = process.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            held = _signal_state(process.pid)  # a signal blocked or ignored is what would explain it
            process.kill()
            out, err = process.communicate()
            pytest.fail(
                f"the stream went on after Ctrl-C (its {held}; the forking thread's {forking}); "
                f"it printed:\n{first}{out}{err}"
            )
    assert VERDICT_LINE.match(first), first + err
    assert process.returncode == 0, err
    assert "stopped" in err and "Traceback" not in err
    assert out.splitlines()[-1].startswith("stream: 1 record, ")


def _signal_state(pid: int | str) -> str:
    """The signals a process (or ``thread-self``) blocks, ignores and catches: masks in hex,
    from /proc."""
    status = Path(f"/proc/{pid}/status")
    if not status.exists():
        return "no /proc"
    return ", ".join(
        line.replace("\t", " ")
        for line in status.read_text().splitlines()
        if line[:6] in ("SigBlk", "SigIgn", "SigCgt")
    )


def test_record_with_coloured_measurement_noise_is_the_simulators(tmp_path: Path):
    """--noise-colour reaches the simulator: the written record equals one simulated directly."""
    args = ["record", "--seed", "8", "--x-noise-std", "500", "--noise-colour", "1.5,0.5"]
    result = invoke_sim(*args, "--format", "npz", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    scenario = Scenario(disturbance_std=SETTINGS.disturbance_std, x_noise_std=500.0, noise_colour=(1.5, 0.5))
    expected = simulate(scenario, SETTINGS.inspection_samples, 8)
    np.testing.assert_array_equal(read_record(tmp_path / "record_0001_none_0.npz").x, expected.x)
    refused = invoke_sim("record", "--noise-colour", "1.5,x", "--out", str(tmp_path))
    assert refused.returncode == 2 and "--noise-colour '1.5,x'" in refused.stderr


def test_structures_create_declares_what_x_and_y_measure(api_server: LiveServer, tenant: Tenant):
    """--excitation/--response and their units reach the service, which stores them; create and
    list print them, and a structure created without them declares none."""
    key = api_server.key(Role.admin, tenant.name)
    args = [
        "--excitation",
        "force",
        "--excitation-unit",
        "kN",
        "--response",
        "acceleration",
        "--response-unit",
        "g",
    ]
    made = invoke_sim(
        "structures", "create", "--name", "bridge", "--fs", "200", *args, key=key, url=api_server.url
    )
    plain = invoke_sim(
        "structures", "create", "--name", "plain", "--fs", "200", "-q", key=key, url=api_server.url
    )
    assert made.returncode == 0 and plain.returncode == 0, made.stderr + plain.stderr
    assert made.stdout.strip().endswith("fs = 200 Hz, force x [kN], acceleration y [g]")
    structure_id = int(made.stdout.split()[1])
    stored = tenant.admin.get(f"/api/v1/structures/{structure_id}").json()
    assert (stored["excitation"], stored["response"]) == (
        {"quantity": "force", "unit": "kN"},
        {"quantity": "acceleration", "unit": "g"},
    )
    assert tenant.admin.get(f"/api/v1/structures/{plain.stdout.strip()}").json()["response"] is None
    listed = invoke_sim("structures", "list", key=key, url=api_server.url).stdout
    assert "'bridge', fs = 200 Hz, force x [kN], acceleration y [g], no verdict yet" in listed
    assert "'plain', fs = 200 Hz, no verdict yet" in listed


def test_structures_update_changes_what_is_given_and_prints_the_refusal_of_a_redeclaration(
    api_server: LiveServer, tenant: Tenant
):
    """The name and an undeclared excitation given after a record was stored: both change, the
    rest stays; then another response quantity is refused with the service's reason, exit 1."""
    key = api_server.key(Role.admin, tenant.name)
    made = tenant.admin.post(
        "/api/v1/structures",
        json={"name": "mast", "fs": 200.0, "response": {"quantity": "acceleration", "unit": "g"}},
    ).json()
    record = {"x": [0.0, 1.0, 0.5] * 100, "y": [0.1, 0.0, -0.1] * 100, "fs": 200.0}
    assert tenant.ingest.post(f"/api/v1/structures/{made['id']}/records", json=record).status_code == 201
    structure = ["--structure", str(made["id"])]
    update = ["structures", "update", *structure, "--name", "mast 2", "--excitation", "force"]
    changed = invoke_sim(*update, "--excitation-unit", "kN", key=key, url=api_server.url)
    assert changed.returncode == 0, changed.stderr
    assert changed.stdout.strip() == (
        f"structure {made['id']} 'mast 2', fs = 200 Hz, force x [kN], acceleration y [g]"
    )
    stored = tenant.admin.get(f"/api/v1/structures/{made['id']}").json()
    assert stored == made | {"name": "mast 2", "excitation": {"quantity": "force", "unit": "kN"}}
    redeclared = invoke_sim(
        "structures", "update", *structure, "--response", "velocity", key=key, url=api_server.url
    )
    assert redeclared.returncode == 1, redeclared.stdout + redeclared.stderr
    assert "409 Conflict: structure 'mast 2' has records" in redeclared.stderr
    assert "can only be completed" in redeclared.stderr and redeclared.stdout == ""
    assert tenant.admin.get(f"/api/v1/structures/{made['id']}").json() == stored
    withdrawn = invoke_sim(
        "structures", "update", *structure, "--withdraw", "response", key=key, url=api_server.url
    )
    assert withdrawn.returncode == 1 and "409 Conflict" in withdrawn.stderr
    assert tenant.admin.get(f"/api/v1/structures/{made['id']}").json() == stored


def test_structures_update_withdraws_a_declaration_of_a_structure_without_records(
    api_server: LiveServer, tenant: Tenant
):
    key = api_server.key(Role.admin, tenant.name)
    made = tenant.admin.post(
        "/api/v1/structures",
        json={"name": "pylon", "fs": 200.0, "response": {"quantity": "acceleration", "unit": "g"}},
    ).json()
    withdrawn = invoke_sim(
        "structures", "update", "--structure", str(made["id"]), "--withdraw", "response",
        key=key, url=api_server.url,
    )  # fmt: skip
    assert withdrawn.returncode == 0, withdrawn.stderr
    assert withdrawn.stdout.strip() == f"structure {made['id']} 'pylon', fs = 200 Hz"
    assert tenant.admin.get(f"/api/v1/structures/{made['id']}").json() == made | {"response": None}


def test_structures_list_prints_every_page(api_server: LiveServer):
    """More structures than a page of the listing holds: every one printed, in the fleet's order."""
    tenant = Tenant.create(api_server)
    names = [f"s{i:03d}" for i in range(fleet.PAGE_SIZE + 1)]
    for name in names:
        assert tenant.admin.post("/api/v1/structures", json={"name": name, "fs": 100.0}).status_code == 201
    listed = invoke_sim(
        "structures", "list", key=api_server.key(Role.viewer, tenant.name), url=api_server.url
    )
    assert listed.returncode == 0, listed.stderr
    assert re.findall(r"'(s\d{3})'", listed.stdout) == names


@pytest.mark.parametrize(
    ("role", "args", "message"),
    [
        (
            Role.ingest,
            ["structures", "create", "--name", "rig", "--fs", "1500"],
            "403 Forbidden: this needs a key of role 'admin' or higher",
        ),
        (Role.admin, ["structures", "create", "--name", "rig", "--fs", "-1"], "422 Unprocessable"),
        (
            Role.admin,
            [
                "structures",
                "create",
                "--name",
                "rig",
                "--fs",
                "1500",
                "--response",
                "strain",
                "--response-unit",
                "µ ε",
            ],
            "the unit 'µ ε' is not allowed: a unit is 1 to 16 printable characters without spaces",
        ),
        (Role.ingest, ["upload", "healthy.csv", "--structure", "999999"], "404 Not Found: structure 999999"),
        (Role.admin, ["train", "baseline", "--structure", "999999", "--records", "1"], "404 Not Found"),
        (
            Role.ingest,
            ["structures", "update", "--structure", "999999", "--name", "r"],
            "403 Forbidden: this needs a key of role 'admin' or higher",
        ),
        (
            Role.admin,
            ["structures", "update", "--structure", "999999", "--name", "r"],
            "404 Not Found: structure 999999 not found",
        ),
    ],
    ids=[
        "ingest creates",
        "negative fs",
        "unit with a space",
        "unknown structure",
        "train unknown structure",
        "ingest updates",
        "update unknown structure",
    ],
)
def test_own_structure_commands_print_the_services_refusal_and_exit_1(
    api_server: LiveServer, tenant: Tenant, role, args, message, tmp_path: Path
):
    (tmp_path / "healthy.csv").write_text("x,y\n1,2\n3,4\n")
    result = invoke_sim(*args, key=api_server.key(role, tenant.name), url=api_server.url, cwd=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr and result.stdout == ""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["upload", "record.txt", "--structure", "1"],
            "send a record file ending in .csv, .json, .npz, .mat",
        ),
        (["upload", "missing.csv", "--structure", "1"], "missing.csv: cannot read it"),
        (
            ["train", "fault-mode", "--structure", "1", "--name", "k2", "--records", "1,2", "--k", "0"],
            "--records names 2 records and --k 1 magnitudes",
        ),
        (["train", "baseline", "--structure", "1", "--records", "one"], "--records takes record ids"),
        (
            ["structures", "create", "--name", "r", "--fs", "1500", "--excitation-unit", "N"],
            "--excitation-unit needs --excitation: say what the signal measures",
        ),
        (
            ["structures", "create", "--name", "r", "--fs", "1500", "--response", "mass"],
            "'mass' is not one of",
        ),
        (
            ["structures", "update", "--structure", "1"],
            "nothing to change: give --name, --description, --excitation, --response or --withdraw",
        ),
        (
            ["structures", "update", "--structure", "1", "--response", "force", "--withdraw", "response"],
            "--response and --withdraw response: give one or the other",
        ),
        (
            ["structures", "update", "--structure", "1", "--response-unit", "g"],
            "--response-unit needs --response",
        ),
    ],
    ids=[
        "suffix",
        "missing file",
        "counts differ",
        "not ids",
        "unit without quantity",
        "unknown quantity",
        "update nothing",
        "declare and withdraw",
        "update unit without quantity",
    ],
)
def test_own_structure_commands_refuse_unusable_input_with_exit_2(args, message, tmp_path: Path):
    (tmp_path / "record.txt").write_text("x,y\n")
    result = invoke_sim(*args, key="nw_x_y", url=f"http://127.0.0.1:{free_port()}", cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr


# --- a training queued as a job, waited for -------------------------------------------------


@pytest.fixture(scope="module")
def queueing(tmp_path_factory) -> Iterator[LiveServer]:
    """A server of its own that queues every training and runs no job until ``run_jobs``."""
    url = f"sqlite:///{tmp_path_factory.mktemp('queueing') / 'narxwatch.db'}"
    with LiveServer(Settings(database_url=url, queue_training_cells=1000, embedded_worker=False)) as server:
        yield server


def training_command(tenant: Tenant, *wait: str, **upload: str) -> tuple[list[str], int]:
    """``train baseline --wait …`` of a new structure's record: the arguments, and the structure."""
    structure_id = tenant.admin.post(
        "/api/v1/structures", json={"name": uuid.uuid4().hex, "fs": 1500.0}
    ).json()["id"]
    record = upload_simulated(tenant.ingest, structure_id, simulated("none", 0.0, [7]), **upload)["id"]
    args = ["train", "baseline", "--structure", str(structure_id), "--records", str(record)]
    return [*args, "--terms", ",".join(RIG_TERMS), "--wait", *wait], structure_id


def training_job(tenant: Tenant, structure_id: int) -> int:
    """The id of the structure's training job, once it is queued."""

    def queued() -> int | None:
        jobs = tenant.admin.get("/api/v1/jobs").json()["items"]
        return next((j["id"] for j in jobs if j["args"].get("structure_id") == structure_id), None)

    return wait_for(queued, 60, "the training's job")  # type: ignore[return-value]


def waited_training(
    server: LiveServer, tenant: Tenant, meanwhile: Callable[[int], None], *wait: str, **upload: str
) -> tuple[subprocess.CompletedProcess[str], int]:
    """``train baseline --wait …`` through the entry point in this process, while another thread
    finds its job once it is queued and does ``meanwhile(job id)``: what the client said, and the
    job's id. (The entry point runs on this thread: it restores the handler of SIGTERM, which only
    the main thread may set.)"""
    args, structure_id = training_command(tenant, *wait, **upload)
    followed: dict[str, int] = {}
    failed: list[BaseException] = []

    def follow() -> None:
        try:
            followed["job"] = training_job(tenant, structure_id)
            meanwhile(followed["job"])
        except BaseException as error:  # raised again on the test's thread
            failed.append(error)

    helper = threading.Thread(target=follow)
    helper.start()
    try:
        said = invoke_sim(*args, key=server.key(Role.admin, tenant.name), url=server.url)
    finally:
        helper.join(60)
    if failed:
        raise failed[0]
    return said, followed["job"]


def test_train_wait_follows_the_queued_job_and_prints_the_version_it_made(queueing: LiveServer):
    tenant = Tenant.create(queueing)
    client, job_id = waited_training(queueing, tenant, lambda _: run_jobs(queueing))
    out, err = client.stdout, client.stderr
    assert client.returncode == 0, err
    job = tenant.admin.get(f"/api/v1/jobs/{job_id}").json()
    assert job["state"] == "done" and job["model"]["name"] == "baseline"
    assert (
        out.splitlines()[0]
        == f"baseline version 1 (model {job['model']['id']}), {len(RIG_TERMS)} terms, active"
    )
    assert f"queued as a job: job {job_id}; waiting for it up to 3600 s" in err


def test_train_wait_gives_up_after_its_time_and_the_job_goes_on(queueing: LiveServer):
    tenant = Tenant.create(queueing)
    client, job_id = waited_training(queueing, tenant, lambda _: None, "--wait-seconds", "1")
    out, err = client.stdout, client.stderr
    assert client.returncode == 1 and out == "", err
    assert f"job {job_id} queued, 0 s" in err  # the progress line
    gave_up = f"job {job_id} is still queued after 1 s; it goes on in the service: follow it at /api/v1/jobs/"
    assert f"{gave_up}{job_id}" in err
    assert tenant.admin.get(f"/api/v1/jobs/{job_id}").json()["state"] == "queued"


def test_train_wait_exits_1_with_the_error_of_a_failed_job(queueing: LiveServer):
    """The record's signals pruned by the retention between the request and its job: the job
    fails, and the client says why."""
    tenant = Tenant.create(queueing)

    def prune_then_run(_: int) -> None:
        policy = {"signal_days": 1, "verdict_days": None}
        assert tenant.admin.put("/api/v1/retention", json=policy).status_code == 200
        with queueing.app.state.sessions() as session:
            retention.prune(
                session, session.scalar(select(Organisation.id).where(Organisation.name == tenant.name))
            )
        run_jobs(queueing)

    client, job_id = waited_training(queueing, tenant, prune_then_run, acquired_at="2020-01-01T00:00:00Z")
    out, err = client.stdout, client.stderr
    job = tenant.admin.get(f"/api/v1/jobs/{job_id}").json()
    assert job["state"] == "failed" and job["error"], job
    assert client.returncode == 1 and out == "", err
    assert f"the training's job {job_id} failed: {job['error']}" in err, err
