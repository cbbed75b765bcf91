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
    # The training prints the baseline it made, the terms chosen for the structure (x[t] among
    # them: the accelerometer feels the force at once), and that it judges records alone.
    made = [line for line in lines if " version " in line]
    assert [line.split(" version ")[0] for line in made] == ["baseline"], lines
    (chosen,) = [line for line in lines if "terms chosen for the structure: " in line]
    assert "x[t]" in chosen.split(": ", 1)[1].split(", "), chosen
    assert "  judges records alone" in lines, lines
    # The new healthy record is healthy and the loosened one an anomaly, with T against its
    # threshold and the severity, both when uploaded and in the verdicts read back (newest first).
    pattern = r"  record \d+  (healthy|anomaly)  T = ([\d.]+) ([>≤]) ([\d.]+)  severity ([\d.]+)"
    verdicts = [found for line in lines if (found := re.search(pattern, line))]
    assert [v.group(1) for v in verdicts] == ["healthy", "anomaly", "anomaly", "healthy"], lines
    for verdict in verdicts:
        status, statistic, sign, threshold, severity = verdict.groups()
        assert (sign == ">") == (status == "anomaly") == (float(statistic) > float(threshold))
        assert float(severity) > 0
    assert "new.csv" in verdicts[0].string and "loosened.csv" in verdicts[1].string
    assert sorted(path.name for path in tmp_path.iterdir()) == sorted(
        [f"healthy{i}.csv" for i in range(1, 11)] + ["new.csv", "loosened.csv"]
    )


def test_the_section_block_is_found_and_holds_the_commands():
    script = section_script(README.read_text(), SECTION)
    for command in ("structures create", "upload", "train baseline", "verdicts"):
        assert f"narxwatch-sim {command}" in script
