"""README.md's "Monitor your own structure" run as printed: its shell block, taken from the README
itself, against the real service over HTTP with the installed ``narxwatch`` and ``narxwatch-sim``
on PATH. Only what the README leaves to the reader is given: the admin key as ``KEY`` and the
service's address as ``NARXWATCH_SIM_URL``, the variables the README names."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from harness.live import LiveServer
from service.security import Role

README = Path(__file__).resolve().parent.parent / "README.md"
SECTION = "## Monitor your own structure"


def section_script(text: str, heading: str) -> str:
    """The first ```sh block after ``heading``, before the next heading."""
    start = text.index(heading) + len(heading)
    following = text.find("\n## ", start)
    section = text[start : None if following < 0 else following]
    block = re.search(r"^```sh\n(.*?)^```$", section, re.S | re.M)
    assert block, f"README.md's {heading!r} holds no ```sh block"
    return block.group(1)


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def test_monitor_your_own_structure_runs_as_printed(api_server: LiveServer, tmp_path: Path):
    script = section_script(README.read_text(), SECTION)
    bin_dir = str(Path(sys.executable).parent)  # where narxwatch and narxwatch-sim are installed
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_SIM_")}
    env |= {
        "KEY": api_server.key(Role.admin),  # a new organisation: it sees only what the script makes
        "NARXWATCH_SIM_URL": api_server.url,
        "PATH": bin_dir + os.pathsep + env.get("PATH", ""),
    }
    result = subprocess.run(
        ["bash", "-e", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    # The trainings print the model versions they made: the baseline and the k2 mode, in that order.
    made = [line for line in lines if " version " in line]
    assert [line.split(" version ")[0] for line in made] == ["baseline", "fault mode k2"], lines
    # The inspected record (k2 loosened by 12 %) is found faulty in mode k2, with k̂ near 12,
    # both when uploaded and in the verdicts read back.
    verdicts = [line for line in lines if re.search(r"  record \d+  (healthy|faulty|unknown_fault)  ", line)]
    assert len(verdicts) == 2, lines
    for line in verdicts:
        found = re.search(r"faulty  mode k2  k̂ = (-?[\d.]+) %", line)
        assert found and 6 < float(found.group(1)) < 18, line
    assert "new.csv" in verdicts[0]
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(
        [f"healthy{i}.csv" for i in (1, 2, 3)] + [f"k2_{k}.csv" for k in (-16, -8, 0, 8, 16)] + ["new.csv"]
    )


def test_the_section_block_is_found_and_holds_the_commands():
    script = section_script(README.read_text(), SECTION)
    for command in ("structures create", "upload", "train baseline", "train fault-mode", "verdicts"):
        assert f"narxwatch-sim {command}" in script
