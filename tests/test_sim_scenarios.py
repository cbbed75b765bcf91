"""``narxwatch-sim stream --scenario``: the fault each record carries, read back from what it wrote.

The records go to files (``--out``), so that the manifest states each record's fault and k and the
files hold the simulated physics, which ``simulate`` with the manifest's seed makes again. The
command runs through the console script's entry point in this process (``harness.cli.invoke``):
what is tested is what it writes and its exit code, not the process, and a process of its own
spends most of its time on imports.
"""

from __future__ import annotations

import csv
import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from harness.cli import invoke
from recordfiles.reader import read_record
from simulator.client.scheduler import Course, ScenarioOptions, Stream
from simulator.simulate import simulate
from simulator.study import StudySettings

SETTINGS = StudySettings()


def stream_to_files(tmp_path: Path, *args: str) -> list[dict[str, str]]:
    tmp_path.mkdir(parents=True, exist_ok=True)
    invoke(
        "stream", "--every", "0", "--per-day", "4", "--seed", "100", "--n", "600", "--out", str(tmp_path),
        *args, cwd=tmp_path, script="narxwatch-sim",
    )  # fmt: skip
    with (tmp_path / "manifest.csv").open(newline="") as handle:
        return list(csv.DictReader(handle))


def magnitudes(rows: list[dict[str, str]]) -> list[tuple[str, float]]:
    return [(row["fault"], float(row["k"])) for row in rows]


def test_healthy_week_has_no_fault_in_any_record(tmp_path: Path):
    rows = stream_to_files(tmp_path, "--scenario", "healthy", "--count", "28")
    assert magnitudes(rows) == [("none", 0.0)] * 28
    assert [int(row["seed"]) for row in rows] == list(range(100, 128))


def test_step_fault_begins_at_its_onset_with_its_size(tmp_path: Path):
    # Four records a day, onset after 1.5 days: records 0–5 healthy, 6–11 with k1 reduced by 8 %.
    rows = stream_to_files(
        tmp_path, "--scenario", "step", "--fault", "k1", "--k", "8", "--onset", "1.5", "--count", "12"
    )
    assert magnitudes(rows) == [("none", 0.0)] * 6 + [("k1", 8.0)] * 6
    # The file holds the physics of its row: the simulator makes the same record from the seed.
    last = read_record(tmp_path / rows[-1]["path"])
    again = simulate(SETTINGS.scenario("k1", 8.0), 600, int(rows[-1]["seed"]))
    np.testing.assert_allclose(last.y, again.y, rtol=1e-12)
    healthy = simulate(SETTINGS.scenario("none", 0.0), 600, int(rows[-1]["seed"]))
    assert not np.allclose(last.y, healthy.y, rtol=1e-3)


def test_drift_grows_at_its_rate_per_day_in_k2(tmp_path: Path):
    rows = stream_to_files(tmp_path, "--scenario", "drift", "--rate", "0.5", "--onset", "1", "--count", "16")
    # 0.5 % a day at four records a day is 0.125 % a record, from day 1 (record 4) on; k2 by default.
    expected = [("none", 0.0)] * 5 + [("k2", 0.125 * i) for i in range(1, 12)]
    assert [(f, round(k, 9)) for f, k in magnitudes(rows)] == expected
    last = read_record(tmp_path / rows[-1]["path"])
    np.testing.assert_allclose(last.y, simulate(SETTINGS.scenario("k2", 1.375), 600, 115).y, rtol=1e-12)


def test_intermittent_fault_shows_in_about_its_duty_share(tmp_path: Path):
    rows = stream_to_files(
        tmp_path, "--scenario", "intermittent", "--k", "10", "--duty", "0.3", "--count", "120"
    )
    shown = [(f, k) for f, k in magnitudes(rows) if k]
    assert set(magnitudes(rows)) == {("none", 0.0), ("k2", 10.0)}
    # Binomial(120, 0.3): mean 36, standard deviation 5.0; four of them either side.
    assert 16 <= len(shown) <= 56
    # Drawn from each record's seed: a second run writes the same course.
    again = stream_to_files(
        tmp_path / "again", "--scenario", "intermittent", "--k", "10", "--duty", "0.3", "--count", "120"
    )
    assert magnitudes(again) == magnitudes(rows)


def test_per_day_sets_the_acquisition_times_whatever_the_pace():
    start = dt.datetime(2030, 1, 1, tzinfo=dt.UTC)
    options = ScenarioOptions(SETTINGS.excitation_std, SETTINGS.disturbance_std, 0.0, 0.0, (), ())
    stream = Stream(options, "none", 0.0, 0.0, 600, 1, 0.0, 3, start, Course.healthy, per_day=4.0)
    assert [plan.acquired_at - start for plan in stream.plans()] == [
        dt.timedelta(hours=h) for h in (0, 6, 12)
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--scenario", "step"], "needs the fault's size"),
        (["--scenario", "drift"], "give --rate"),
        (["--scenario", "drift", "--rate", "1", "--k", "3"], "give --rate, not --k"),
        (["--scenario", "healthy", "--fault", "k1"], "leave out --fault"),
        (["--scenario", "step", "--k", "5", "--drift", "1"], "--scenario drift --rate"),
        (["--scenario", "intermittent", "--k", "5", "--duty", "0"], "--duty"),
        (["--scenario", "step", "--k", "5", "--onset", "-1"], "--onset"),
        (["--rate", "1"], "belongs to a --scenario"),
        (["--scenario", "drift", "--rate", "10", "--count", "100"], "would remove the spring entirely"),
        (["--scenario", "healthy", "--per-day", "0"], "--per-day"),
    ],
)
def test_options_that_do_not_fit_the_scenario_exit_2(args, message, tmp_path: Path):
    # A few records at once: were the options taken, the stream would end, not wait in this process.
    given = ["--every", "0", "--out", str(tmp_path)]
    given += [] if "--per-day" in args else ["--per-day", "4"]
    given += [] if "--count" in args else ["--count", "3"]
    result = invoke("stream", *given, *args, cwd=tmp_path, check=False, script="narxwatch-sim")
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert list(tmp_path.iterdir()) == []
