"""``narxwatch db upgrade``, ``keys create``, ``demo-seed`` and ``serve``, run as a user runs them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from live import free_port, wait_until_serving

BIN = Path(sys.executable).parent
NARXWATCH = shutil.which("narxwatch", path=str(BIN))


def run(*args: str, env: dict[str, str], check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run([NARXWATCH, *args], env=env, capture_output=True, text=True, timeout=300)
    if check:
        assert result.returncode == 0, result.stderr
    return result


@pytest.fixture(scope="module")
def seeded(tmp_path_factory) -> dict[str, str]:
    """An environment whose SQLite database holds the demo, seeded twice."""
    env = {**os.environ, "NARXWATCH_DATABASE_URL": f"sqlite:///{tmp_path_factory.mktemp('svc') / 'n.db'}"}
    run("db", "upgrade", env=env)
    first = run("demo-seed", env=env)
    second = run("demo-seed", env=env)
    env["FIRST_SEED"], env["SECOND_SEED"] = first.stdout, second.stdout
    return env


def test_demo_seed_is_idempotent(seeded):
    assert "k2 experiments" in seeded["FIRST_SEED"]
    # The second run finds the demo and trains nothing.
    assert "experiments" not in seeded["SECOND_SEED"]
    assert "is structure 1" in seeded["SECOND_SEED"]


def test_keys_create_prints_a_working_key_once(seeded):
    key = run("keys", "create", "--org", "demo", "--role", "viewer", env=seeded).stdout.strip()
    assert key.startswith("nw_") and len(key) > 40
    other = run("keys", "create", "--org", "demo", "--role", "viewer", env=seeded).stdout.strip()
    assert other != key


def test_keys_create_refuses_an_unknown_role(seeded):
    result = run("keys", "create", "--org", "demo", "--role", "root", env=seeded, check=False)
    assert result.returncode == 2 and "unknown role 'root'" in result.stderr


def test_serve_answers_with_the_seeded_demo(seeded):
    port = free_port()
    admin = run("keys", "create", "--org", "demo", "--role", "admin", env=seeded).stdout.strip()
    server = subprocess.Popen(
        [NARXWATCH, "serve", "--port", str(port)],
        env=seeded,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        base = f"http://127.0.0.1:{port}"
        wait_until_serving(base, server, 60, lambda: "narxwatch serve did not start")
        assert httpx.get(f"{base}/readyz").json() == {"status": "ready"}
        headers = {"Authorization": f"Bearer {admin}"}
        structures = httpx.get(f"{base}/api/v1/structures", headers=headers).json()
        assert [s["name"] for s in structures] == ["2-DOF rig (paper parameters)"]
        models = httpx.get(f"{base}/api/v1/structures/{structures[0]['id']}/models", headers=headers).json()
        assert sorted((m["name"], m["active"]) for m in models) == [
            ("baseline", True),
            ("k1", True),
            ("k2", True),
        ]
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)
