"""``narxwatch refine`` as a user runs it: Silverbox and simulated records with an undeclared effect."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_cli import PNG_MAGIC, run

REPORT_KEYS = {"declared", "effects_added", "before", "after", "refined", "data", "validation"}
ASSESSMENT_KEYS = {"one_step_rms", "free_run_rms", "ljung_box_p", "diagnostics"}


def test_silverbox_json_report_and_plot(silverbox_dir, tmp_path):
    figure = tmp_path / "refine.png"
    result = run(
        "refine", str(silverbox_dir / "SNLS80mV.csv"), "--format", "silverbox", "--declared", "linear:4,4",
        "--validate", str(silverbox_dir / "Schroeder80mV.csv"), "--json", "--plot", str(figure), cwd=tmp_path,
    )  # fmt: skip
    report = json.loads(result.stdout)
    assert set(report) == REPORT_KEYS
    assert set(report["before"]) == set(report["after"]) == ASSESSMENT_KEYS
    # README lists what the loop adds, in this order.
    names = [effect["name"] for effect in report["effects_added"]]
    assert names == [
        "missing_lags", "cubic_damping", "offset", "cubic_stiffness", "quadratic_stiffness",
        "unmeasured_nonlinearity", "periodic_disturbance", "power_law_damping", "input_nonlinearity",
        "quadratic_damping",
    ]  # fmt: skip
    assert set(report["effects_added"][0]["terms"]) == {"x[t]", "y[t-5]", "y[t-6]"}
    for effect in report["effects_added"]:
        assert effect["terms"] and set(effect["evidence"]) >= {"explained_fraction", "p_values", "level"}
        assert max(effect["evidence"]["p_values"]) < effect["evidence"]["level"]
    # The official split, and the linear ARX as declared.
    assert report["data"]["estimation"] == [40650, 105712] and report["data"]["test"] == [100, 40575]
    assert report["declared"]["terms"][:4] == ["y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]"]
    # README's Silverbox table: one-step 1.20 → 0.085 mV, free run 14.39 → 0.324 mV on the full arrow,
    # with a margin of about 10 % for arithmetic differences between machines.
    assert 1.1e-3 < report["before"]["one_step_rms"] < 1.3e-3 and report["after"]["one_step_rms"] <= 0.094e-3
    assert 13e-3 < report["before"]["free_run_rms"] < 16e-3 and report["after"]["free_run_rms"] <= 0.36e-3
    # The linear model's residual fails the nonlinearity tests; every test is reported by name.
    before = report["before"]["diagnostics"]
    assert not before["passed"] and before["failed"]
    assert set(before["correlation_tests"]) >= {"phi_ee", "phi_ue", "phi_u2'e"}
    # The refined model, not refitted, on the independent Schroeder-phase multisine record.
    (schroeder,) = report["validation"]
    assert schroeder["path"].endswith("Schroeder80mV.csv")
    # README: 18.92 → 0.434 mV.
    assert (
        17e-3 < schroeder["before"]["free_run_rms"] < 21e-3 and schroeder["after"]["free_run_rms"] <= 0.48e-3
    )
    assert figure.read_bytes().startswith(PNG_MAGIC)


def test_simulated_quadratic_stiffness_is_named_and_the_table_printed(tmp_path):
    run(
        "simulate", "--n", "12000", "--seed", "3", "--disturbance-std", "200",
        "--effect", "quadratic_stiffness2=3e5", "--out", "record.csv", cwd=tmp_path,
    )  # fmt: skip
    report = json.loads(run("refine", "record.csv", "--json", cwd=tmp_path).stdout)
    assert report["effects_added"][0]["name"] == "quadratic_stiffness"
    assert report["after"]["one_step_rms"] <= report["before"]["one_step_rms"] / 2
    table = run("refine", "record.csv", cwd=tmp_path).stdout
    assert "1. quadratic_stiffness" in table and "before" in table and "after" in table


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--declared", "linear:4"], "linear:NY,NX"),
        (["--estimation", "0-100"], "write A:B"),
        (["--test", "100:999999"], "does not lie within"),
        (["--declared", "y[t-1],z[t-2]"], "cannot read term"),
        (["--initial", "-1"], "initial samples must be 0 or more"),
    ],
)
def test_bad_options_are_refused_with_a_message(silverbox_dir, tmp_path, args, message):
    data = str(silverbox_dir / "SNLS80mV.csv")
    result = run("refine", data, "--format", "silverbox", *args, cwd=tmp_path, check=False)
    assert result.returncode == 2 and message in result.stderr, result.stderr


def test_a_file_that_is_not_silverbox_is_named(tmp_path: Path):
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    result = run("refine", "other.csv", "--format", "silverbox", cwd=tmp_path, check=False)
    assert result.returncode == 2 and "other.csv" in result.stderr and "V1" in result.stderr
