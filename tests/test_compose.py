"""docker-compose.yml: read as Compose reads it, and the commands of its one-shot services run as
they would run in their containers (no Docker engine is needed: the image runs these commands).

`docker compose up` must seed the demo and hand the simulator a key without the user's help.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from harness.cli import ENTRY_POINTS, invoke
from harness.live import LiveServer
from service.config import Settings

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def mounted(service: dict, volume: str) -> str:
    """Where ``service`` mounts the named ``volume``."""
    (target,) = [spec.split(":")[1] for spec in service.get("volumes", []) if spec.split(":")[0] == volume]
    return target


def in_container(command: list[str], mounts: dict[str, Path]) -> list[str]:
    """``command`` with the container's paths replaced by the test's folders, run from this venv."""
    program = shutil.which(command[0], path=str(BIN))
    assert program, f"{command[0]} is not a console script of this project"
    arguments = command[1:]
    for inside, outside in mounts.items():
        arguments = [a.replace(inside, str(outside)) for a in arguments]
    return [program, *arguments]


def here(command: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``command`` (one without mounted paths) through its console script's entry point in this
    process: what the container runs, without a new process's seconds of imports."""
    assert command[0] in ENTRY_POINTS, f"{command[0]} is not a console script of this project"
    return invoke(*command[1:], cwd=cwd, script=command[0], environ=env, check=False)


def test_the_services_start_in_order_and_share_the_simulators_key(compose: dict):
    services = compose["services"]
    seed, simulator = services["seed"], services["simulator"]
    assert seed["depends_on"] == {"migrate": {"condition": "service_completed_successfully"}}
    assert seed["restart"] == "no"
    assert simulator["depends_on"] == {
        "api": {"condition": "service_healthy"},
        "seed": {"condition": "service_completed_successfully"},
    }
    key_file = seed["command"][seed["command"].index("--key-file") + 1]
    (keys,) = [v.split(":")[0] for v in simulator["volumes"]]
    assert keys in compose["volumes"]
    assert key_file.startswith(mounted(seed, keys) + "/")
    assert simulator["environment"]["NARXWATCH_SIM_API_KEY_FILE"] == key_file
    assert mounted(simulator, keys) == mounted(seed, keys)
    assert simulator["volumes"] == [f"{keys}:{mounted(seed, keys)}:ro"]
    database = services["api"]["environment"]["NARXWATCH_DATABASE_URL"]
    assert seed["environment"]["NARXWATCH_DATABASE_URL"] == database, (
        "the seed service seeds the api's database"
    )


def test_every_service_of_the_service_reads_one_sealing_key_file_on_a_volume_they_share(compose: dict):
    """The API seals webhooks' secrets and the workers unseal them to sign each delivery: each
    with a key of its own, nothing a worker sent would be signed. The migrations seal too."""
    services = compose["services"]
    ours = [name for name, service in services.items() if service.get("command", [""])[0] == "narxwatch"]
    assert {"migrate", "api", "worker-1", "worker-2"} <= set(ours)
    key_files = {services[name]["environment"]["NARXWATCH_SECRET_KEY_FILE"] for name in ours}
    (key_file,) = key_files
    folders = {mounted(services[name], "sealing") for name in ours}
    assert folders == {str(Path(key_file).parent)} and "sealing" in compose["volumes"]


@pytest.fixture(scope="module")
def seeded(compose: dict, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    """The seed service's command, run twice as `docker compose up` would on each start."""
    folder = tmp_path_factory.mktemp("compose")
    seed = compose["services"]["seed"]
    mounts = {mounted(seed, "keys"): folder / "keys"}
    (folder / "keys").mkdir()
    url = f"sqlite:///{folder / 'narxwatch.db'}"
    env = {**os.environ, "NARXWATCH_DATABASE_URL": url}
    runs = [
        subprocess.run(
            in_container(seed["command"], mounts), env=env, capture_output=True, text=True, timeout=600
        )
        for _ in range(2)
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
    yield {"runs": runs, "url": url, "mounts": mounts, "key_file": folder / "keys" / "simulator.key"}


@pytest.fixture(scope="module")
def api(seeded: dict) -> Iterator[LiveServer]:
    """The api service on the seeded database."""
    with LiveServer(Settings(database_url=seeded["url"])) as server:
        yield server


def test_the_seed_service_seeds_the_demo_and_writes_and_prints_one_key(seeded: dict):
    first, second = seeded["runs"]
    key = seeded["key_file"].read_text().strip()
    assert key.startswith("nw_")
    assert seeded["key_file"].stat().st_mode & 0o077 == 0, "the key file is the owner's only"
    assert "k2 experiments" in first.stdout and key in first.stdout, "the first start prints the key"
    assert "experiments" not in second.stdout and key not in second.stdout
    assert seeded["key_file"].read_text().strip() == key, "a restart keeps the key it made"


def test_the_simulator_posts_with_the_key_the_seed_service_wrote(
    compose: dict, seeded: dict, api: LiveServer, tmp_path: Path
):
    simulator = compose["services"]["simulator"]
    command = [api.url if part == "http://api:8000" else part for part in simulator["command"]]
    command[command.index("--count") + 1] = "2"
    command[command.index("--every") + 1] = "0"
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_")}
    env["NARXWATCH_SIM_API_KEY_FILE"] = simulator["environment"]["NARXWATCH_SIM_API_KEY_FILE"]
    for inside, outside in seeded["mounts"].items():
        env["NARXWATCH_SIM_API_KEY_FILE"] = env["NARXWATCH_SIM_API_KEY_FILE"].replace(inside, str(outside))
    result = here(command, env, tmp_path)
    assert result.returncode == 0, result.stderr
    assert "stream: 2 records" in result.stdout, result.stdout
    assert len(re.findall(r"record \d+  (?:healthy|faulty|unknown)", result.stdout)) == 2, result.stdout


def test_the_seed_service_says_how_to_make_an_admin_key_and_that_key_creates_structures(
    compose: dict, seeded: dict, api: LiveServer, tmp_path: Path
):
    """The seed's key is an ingest key, which cannot create a structure: its first start prints
    the command for an admin key, which docker-compose.yml's header gives as run in the api service."""
    first, second = seeded["runs"]
    (printed,) = re.findall(r"narxwatch keys create --org \S+ --role admin", first.stdout)
    assert printed not in second.stdout
    assert f"docker compose exec api {printed}" in (ROOT / "docker-compose.yml").read_text()
    env = {**os.environ, "NARXWATCH_DATABASE_URL": seeded["url"]}
    made = here(printed.split(), env, tmp_path)
    assert made.returncode == 0, made.stderr
    with api.client(made.stdout.strip()) as admin:
        created = admin.post("/api/v1/structures", json={"name": "my rig", "fs": 1500.0})
        assert created.status_code == 201, created.text
        listed = admin.get("/api/v1/structures").json()
    assert {structure["name"] for structure in listed} >= {"my rig"} and len(listed) >= 2, "the demo's too"
