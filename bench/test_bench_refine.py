"""Targets: ``narxwatch refine`` on Silverbox ≤ 15 s end to end; a loop over 100 000 samples ≤ 60 s;
on 100 clean records of the 2-DOF rig no effect added in at least 95 (a study, timed once).

The end-to-end figure runs the installed console script as a user does (reading the 131 072-row
CSV, the loop from a linear ARX(4,4), the held-out assessment with every residual test, the JSON
report). The in-process figures split it: the loop alone, and the loop with its assessment.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from harness.prerequisites import benchmark_file
from models.effects import linear_terms
from models.refinement import refine, refine_record
from recordfiles.reader import parse_silverbox
from simulator.simulate import Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS

NARXWATCH = shutil.which("narxwatch", path=str(Path(sys.executable).parent))
ESTIMATION, ARROW, INITIAL = (40650, 105712), (100, 40575), 50


@pytest.fixture(scope="module")
def silverbox():
    return parse_silverbox(benchmark_file("silverbox", "SNLS80mV.csv").read_bytes())


@pytest.mark.benchmark(group="refine: Silverbox, linear ARX(4,4) (target <= 15 s end to end)")
def test_narxwatch_refine_end_to_end(benchmark, tmp_path) -> None:
    benchmark.extra_info["target_median_s"] = 15.0
    command = [
        NARXWATCH,
        "refine",
        str(benchmark_file("silverbox", "SNLS80mV.csv")),
        "--format",
        "silverbox",
        "--declared",
        "linear:4,4",
        "--json",
    ]

    result = benchmark.pedantic(
        subprocess.run, args=(command,), kwargs={"capture_output": True, "text": True}, rounds=3, iterations=1
    )

    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["after"]["free_run_rms"] <= 2.5e-3 < 10e-3 < report["before"]["free_run_rms"]


@pytest.mark.benchmark(group="refine: Silverbox, the measured benchmarks page's table")
def test_silverbox_table_of_the_measured_benchmarks_page(benchmark, tmp_path) -> None:
    """docs/benchmarks/measured.md's Silverbox row, through the command as it prints it: the
    effects in their order and the errors on the arrow and the Schroeder multisine, within about
    10 % for arithmetic differences between machines."""
    silverbox = benchmark_file("silverbox", "SNLS80mV.csv").parent
    command = [
        NARXWATCH, "refine", str(silverbox / "SNLS80mV.csv"), "--format", "silverbox",
        "--declared", "linear:4,4", "--validate", str(silverbox / "Schroeder80mV.csv"), "--json",
    ]  # fmt: skip

    result = benchmark.pedantic(
        subprocess.run, args=(command,), kwargs={"capture_output": True, "text": True}, rounds=1, iterations=1
    )

    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    names = [effect["name"] for effect in report["effects_added"]]
    assert names == [
        "missing_lags", "cubic_damping", "offset", "cubic_stiffness", "quadratic_stiffness",
        "unmeasured_nonlinearity", "moving_average_noise", "power_law_damping", "input_nonlinearity",
        "quadratic_damping",
    ]  # fmt: skip
    assert set(report["effects_added"][0]["terms"]) == {"x[t]", "y[t-5]", "y[t-6]"}
    # One-step 1.20 → 0.187 mV and free run 14.39 → 0.227 mV on the arrow; 18.92 → 0.282 mV on
    # the Schroeder-phase multisine, the refined model not refitted.
    assert 1.1e-3 < report["before"]["one_step_rms"] < 1.3e-3 and report["after"]["one_step_rms"] <= 0.21e-3
    assert 13e-3 < report["before"]["free_run_rms"] < 16e-3 and report["after"]["free_run_rms"] <= 0.25e-3
    _, schroeder = report["tests"]
    assert (
        17e-3 < schroeder["before"]["free_run_rms"] < 21e-3 and schroeder["after"]["free_run_rms"] <= 0.31e-3
    )


@pytest.mark.benchmark(group="refine: Silverbox, linear ARX(4,4) (target <= 15 s end to end)")
def test_refinement_loop(benchmark, silverbox) -> None:
    a, b = ESTIMATION
    result = benchmark.pedantic(
        refine, args=([(silverbox.x[a:b], silverbox.y[a:b])], linear_terms(4, 4)), rounds=3, iterations=1
    )
    assert "cubic_stiffness" in [effect.name for effect in result.effects_added]


@pytest.mark.benchmark(group="refine: Silverbox, linear ARX(4,4) (target <= 15 s end to end)")
def test_refinement_with_assessment(benchmark, silverbox) -> None:
    args = (silverbox.x, silverbox.y, linear_terms(4, 4), [ESTIMATION], ARROW, INITIAL, 0.01, silverbox.fs)
    report = benchmark.pedantic(refine_record, args=args, rounds=3, iterations=1)
    assert report.after.free_run_rms <= 2.5e-3


@pytest.mark.benchmark(group="refine: 100 000 estimation samples (target <= 60 s)")
def test_refinement_loop_on_100_000_samples(benchmark) -> None:
    """The loop from SPEC §2's structure on 100 000 simulated samples of the 2-DOF rig with a
    cubic spring on the unmeasured mass and a 20 N unmeasured force."""
    scenario = Scenario(disturbance_std=20.0, effects=Effects(cubic_stiffness1=4e6))
    record = simulate(scenario, 100_000, seed=3)
    result = benchmark.pedantic(refine, args=([(record.x, record.y)], EXACT_TERMS), rounds=1, iterations=1)
    # On the 80 000 samples the loop chooses on (the rest held out), moving-average noise ranks
    # first in the one-step order and runs free as the start does; the nonlinearity, which takes
    # most of the check blocks' free run off, takes the round from it and noise comes after.
    process = [effect.name for effect in result.effects_added if effect.name != "moving_average_noise"]
    assert process[0] == "unmeasured_nonlinearity", process
    assert result.held_out is not None and result.held_out.kept


@pytest.mark.slow
@pytest.mark.benchmark(group="refine: 100 clean records (no effect added in >= 95)")
def test_on_100_clean_records_no_effect_is_added_in_at_least_95(benchmark) -> None:
    """SPEC §2's structure on 100 records of the rig as it is (800 N unmeasured force, 8000
    samples each): the loop must leave at least 95 alone (tests/test_refinement.py runs 20)."""

    def count_added() -> int:
        added = 0
        for seed in range(100):
            record = simulate(Scenario(disturbance_std=800.0), 12_000, seed=1000 + seed)
            added += bool(refine([(record.x[:8000], record.y[:8000])], EXACT_TERMS).effects_added)
        return added

    added = benchmark.pedantic(count_added, rounds=1, iterations=1)
    benchmark.extra_info["records_with_an_effect_added"] = added
    assert added <= 5, f"an effect was added to {added} of 100 clean records"
