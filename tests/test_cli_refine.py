"""``narxwatch refine`` on Silverbox and on simulated records with an undeclared effect: through the
console script's entry point in this process (``test_cli.invoke``), and as a process where the
process is what is tested (a terminal, one CPU, signals). The loop runs in this process alone
(--jobs 1), its report the same in processes (the --jobs test), but where its processes are what
is tested: --jobs 2, the signals, and the terminal's run with the default, a process a CPU."""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import pty
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from harness.cli import NARXWATCH, PNG_MAGIC, invoke
from harness.extrapolating import growing_steps
from harness.multisines import measured
from models.coverage import coverage
from models.effects import candidate_effects
from models.explanation import explain_refinement
from models.narx import NARX, fit_narx
from models.output_error import RESTLESS
from models.refinement import refine_record
from models.terms import parse_terms, regressor_matrix
from recordfiles.reader import read_record
from recordfiles.writer import dump_csv
from service.cli.modelfiles import signal_layout
from service.cli.refine_figure import draw_refinement_figure
from simulator.theory import EXACT_TERMS

REPORT_KEYS = {
    "declared", "orders_chosen", "effects_added", "effects_withdrawn", "before", "after", "tests", "refined",
    "notes", "data", "check_free_run_rms", "noise_floor", "held_out", "explanation",
    "rounds", "settled_from", "amplitude_range",
}  # fmt: skip
ASSESSMENT_KEYS = {"one_step_rms", "free_run_rms", "ljung_box_p", "diagnostics", "skipped_tests", "diverged"}
HELD_OUT_KEYS = {
    "samples", "start_free_run_rms", "refined_free_run_rms", "gain", "threshold", "level", "diverged",
    "refined_returned", "best_tried", "orders_saw_tails", "kinks_beyond", "set_aside",
    "all_rounds_free_run_rms",
}  # fmt: skip


# The Schroeder-phase record's first samples, judged on: the refined model not refitted on a
# second measured record of the benchmark's format.
SCHROEDER_SAMPLES = 20_000


def test_silverbox_json_report_and_plot(silverbox_dir, tmp_path):
    """The command's wiring on a measured record: the benchmark's format, estimation and test
    parts chosen, a record to validate on, the JSON report and the figure. The loop runs on 3000
    samples of the estimation data and judges on the Schroeder-phase record's first 20 000, in
    the benchmark's format as its file has them (its overload flags in the first row): enough
    for the linear model of the nonlinear circuit to be refined and judged better on each, by
    far (its free run at a tenth of the start's and less). In this process alone: the loop's
    pieces in processes are the --jobs test's. The whole loop on the benchmark's own split, and
    the figures of docs/benchmarks/measured.md, are bench/test_bench_refine.py's."""
    lines = (silverbox_dir / "Schroeder80mV.csv").read_text().splitlines(keepends=True)
    (tmp_path / "Schroeder.csv").write_text("".join(lines[: 1 + SCHROEDER_SAMPLES]))
    figure = tmp_path / "refine.png"
    result = invoke(
        "refine", str(silverbox_dir / "SNLS80mV.csv"), "--format", "silverbox", "--declared", "linear:4,4",
        "--estimation", "40650:43650", "--test", "100:8100", "--validate", "Schroeder.csv",
        "--json", "--plot", str(figure), "--jobs", "1", cwd=tmp_path,
    )  # fmt: skip
    report = json.loads(result.stdout)
    assert set(report) == REPORT_KEYS
    assert set(report["before"]) == set(report["after"]) == ASSESSMENT_KEYS
    for effect in report["effects_added"]:
        assert effect["terms"] and set(effect["evidence"]) >= {"explained_fraction", "p_values", "level"}
        assert max(effect["evidence"]["p_values"]) < effect["evidence"]["level"]
    assert report["effects_added"], "the linear model of a nonlinear circuit is refined"
    # The loop runs on 40650:43050, the last 600 samples held out (and fitted once judged).
    assert report["data"]["estimation"] == [
        {"path": str(silverbox_dir / "SNLS80mV.csv"), "x": "V1", "y": "V2", "samples": [40650, 43650]}
    ]
    assert report["data"]["unit"] == "V"  # the benchmark's signals are voltages
    arrow, schroeder = report["tests"]
    assert arrow["samples"] == [100, 8100] and arrow["before"] == report["before"]
    assert report["declared"]["terms"][:4] == ["y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]"]
    assert report["refined"]["estimator"] == "output error"
    assert report["after"]["free_run_rms"] < report["before"]["free_run_rms"]
    # The linear model's residual fails the nonlinearity tests; every test is reported by name.
    before = report["before"]["diagnostics"]
    assert not before["passed"] and before["failed"]
    assert set(before["correlation_tests"]) >= {"phi_ee", "phi_ue", "phi_u2'e"}
    # The refined model, not refitted, on the Schroeder-phase multisine, read whole.
    assert schroeder["path"] == "Schroeder.csv" and schroeder["samples"] == [0, SCHROEDER_SAMPLES]
    assert schroeder["after"]["free_run_rms"] < schroeder["before"]["free_run_rms"]
    assert arrow["verdict"] == schroeder["verdict"] == "better"
    # The refined model won on the estimation part's held-out tail, which no choice saw.
    assert set(report["held_out"]) == HELD_OUT_KEYS and report["held_out"]["samples"] == 600
    assert report["held_out"]["orders_saw_tails"] is False  # a long record's orders are chosen on its heads
    assert report["held_out"]["refined_returned"] and not report["held_out"]["diverged"]
    assert report["held_out"]["kinks_beyond"] == []  # Silverbox's output crosses zero
    assert report["held_out"]["gain"] > report["held_out"]["threshold"] > 0
    assert figure.read_bytes().startswith(PNG_MAGIC)


def test_the_effect_found_is_named_and_the_table_printed_with_each_stage_on_a_terminal(
    simulated_records: Path,
):
    """On a terminal the loop shows each stage as it runs (on stderr); the table goes to stdout,
    with the unit given beside the figures."""
    table, terminal = run_on_terminal(
        "refine", "e1.csv", "--declared", "2dof", "--unit", "m", cwd=simulated_records
    )
    (first,) = [line for line in table.splitlines() if line.startswith("1. ")]
    assert first.startswith("1. quadratic_stiffness (") and "decided by the one-step criterion" in first, (
        table
    )
    (row,) = [line.split() for line in table.splitlines() if line.endswith("e1.csv [4000:6000]")]
    assert float(row[1]) <= float(row[0]) / 2, "the one-step RMS at least halves"
    # The unit given is printed with the figures: the table's columns, each effect's check
    # figures and the output's RMS its shares are of.
    assert "one-step RMS [m]" in table and "free-run RMS [m]" in table
    assert re.search(r"check blocks' free run \S+ → \S+ m;", table), table
    assert re.search(r"shares of the output's RMS \(\S+ m\) on e1\.csv", table), table
    # Each round's choice: the candidates compared, the fall and the fall needed.
    assert re.search(r"  1: \d+ tried, fall \S+% against \S+% needed → quadratic_stiffness", table), table
    stages = (
        f"round 1: scoring {len(candidate_effects(EXACT_TERMS))} families",
        "round 1: quadratic_stiffness on the check blocks",
        "round 2: scoring",
        "judging both models on the test part",
    )
    assert all(stage in terminal for stage in stages), terminal[-2000:]
    assert "round 1" not in table


def run_on_terminal(*args: str, cwd: Path) -> tuple[str, str]:
    """The console script with its stderr on a pseudo-terminal and its stdout on a pipe: what it
    printed to each (the terminal's text with its control sequences)."""
    assert NARXWATCH, "the narxwatch console script is not installed next to this Python"
    controller, terminal = pty.openpty()
    shown = bytearray()

    def drain() -> None:  # a full terminal buffer would block the writer
        with contextlib.suppress(OSError):  # EIO once the writer has gone
            while chunk := os.read(controller, 4096):
                shown.extend(chunk)

    reader = threading.Thread(target=drain)
    reader.start()
    try:
        result = subprocess.run(
            [NARXWATCH, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=terminal, text=True, timeout=300
        )
    finally:
        os.close(terminal)
        reader.join(timeout=10)
        os.close(controller)
    assert result.returncode == 0, shown.decode(errors="replace")
    return result.stdout, shown.decode(errors="replace")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--declared", "linear:4"], "linear:NY,NX"),
        (["--estimation", "0-100"], "write A:B"),
        (["--test", "100:999999"], "does not lie within"),
        (["--declared", "y[t-1],z[t-2]"], "cannot read term"),
        (["--initial", "-1"], "initial samples must be 0 or more"),
        (["--jobs", "0"], "--jobs must be 1 or more"),
        (["--jobs", "100000"], "twice the CPUs this command may use; got 100000"),
    ],
)
def test_bad_options_are_refused_with_a_message(silverbox_dir, tmp_path, args, message):
    data = str(silverbox_dir / "SNLS80mV.csv")
    result = invoke("refine", data, "--format", "silverbox", *args, cwd=tmp_path, check=False)
    assert result.returncode == 2 and message in result.stderr, result.stderr


def test_a_file_that_is_not_silverbox_is_named(tmp_path: Path):
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    result = invoke("refine", "other.csv", "--format", "silverbox", cwd=tmp_path, check=False)
    assert result.returncode == 2 and "other.csv" in result.stderr and "V1" in result.stderr


@pytest.fixture(scope="module")
def simulated_records(tmp_path_factory) -> Path:
    """Four 6000-sample records of the 2-DOF rig with an undeclared quadratic spring, written by
    `narxwatch simulate`: e1, e2 to estimate on, v1, v2 to judge on; and loud, whose force is
    twice as strong."""
    folder = tmp_path_factory.mktemp("records")
    for seed, name in enumerate(("e1", "e2", "v1", "v2", "loud"), start=21):
        invoke(
            "simulate", "--n", "6000", "--seed", str(seed), "--disturbance-std", "200",
            "--effect", "quadratic_stiffness2=3e5", "--out", f"{name}.csv",
            *(("--excitation-std", "50000") if name == "loud" else ()), cwd=folder,
        )  # fmt: skip
    return folder


@pytest.fixture(scope="module")
def clean_records(tmp_path_factory) -> Path:
    """Three 6000-sample records of the 2-DOF rig with nothing undeclared (e1, e2 and v1), for the
    command's wiring of records, parts, glitches and rates, where what the loop adds is not what is
    checked: from SPEC §2's structure it adds nothing, in one round."""
    folder = tmp_path_factory.mktemp("clean")
    for seed, name in enumerate(("e1", "e2", "v1"), start=21):
        invoke(
            "simulate", "--n", "6000", "--seed", str(seed), "--disturbance-std", "200",
            "--out", f"{name}.csv", cwd=folder,
        )  # fmt: skip
    return folder


def declared_fit(folder: Path, names: list[str]) -> NARX:
    """SPEC §2's structure fitted by least squares on the named records, independently of refine."""
    records = [read_record(folder / f"{name}.csv") for name in names]
    return fit_narx([(r.x, r.y) for r in records], EXACT_TERMS)


def signals(folder: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    record = read_record(folder / f"{name}.csv")
    return record.x, record.y


def free_run_rms(model: NARX, folder: Path, name: str) -> float:
    """The model's free run over the whole record, from its first L outputs."""
    record = read_record(folder / f"{name}.csv")
    x, y = record.x, record.y
    L = model.max_lag
    return float(np.sqrt(np.mean((model.simulate(x, y)[L:] - y[L:]) ** 2)))


def refine_report(*args: str, cwd: Path) -> dict:
    """The JSON report of ``narxwatch refine`` with ``args``, run in ``cwd``."""
    return json.loads(invoke("refine", *args, "--json", cwd=cwd).stdout)


TWO_RECORDS = ("e1.csv", "e2.csv", "--declared", "2dof", "--validate", "v1.csv", "v2.csv")


@pytest.fixture(scope="module")
def two_record_report(simulated_records: Path) -> dict:
    """The JSON report of the loop on e1 and e2, judged on v1 and v2, in this one process (the
    test of --jobs compares two processes' with it)."""
    return refine_report(*TWO_RECORDS, "--jobs", "1", cwd=simulated_records)


# A unit matplotlib would parse as mathtext, and fail to draw ($\frac$), were it not escaped.
MATHTEXT_UNIT = "$\\frac$"


@pytest.fixture(scope="module")
def two_record_table(simulated_records: Path) -> subprocess.CompletedProcess[str]:
    """The table of the same loop, --validate repeated, judged on loud too, in a unit written as
    mathtext would be, with its figure drawn to two-records.png."""
    return invoke(
        "refine", "e1.csv", "e2.csv", "--declared", "2dof", "--validate", "v1.csv", "--validate", "v2.csv",
        "loud.csv", "--unit", MATHTEXT_UNIT, "--plot", "two-records.png", "--jobs", "1",
        cwd=simulated_records,
    )  # fmt: skip


def test_several_estimation_records_and_each_validation_record_judged_whole(
    simulated_records: Path, two_record_report: dict, two_record_table: subprocess.CompletedProcess[str]
):
    report = two_record_report
    assert set(report) == REPORT_KEYS
    assert report["data"]["estimation"] == [
        {"path": "e1.csv", "x": "x", "y": "y", "samples": [0, 6000]},
        {"path": "e2.csv", "x": "x", "y": "y", "samples": [0, 6000]},
    ]
    # Estimation on both records at once: the declared model is the least-squares fit on both,
    # not on either alone.
    both = declared_fit(simulated_records, ["e1", "e2"])
    np.testing.assert_allclose(report["declared"]["theta"], both.theta, rtol=1e-9)
    alone = declared_fit(simulated_records, ["e1"])
    assert not np.allclose(report["declared"]["theta"], alone.theta, rtol=1e-6)
    # One before/after a validation record, each judged over the whole record.
    terms = parse_terms(report["refined"]["terms"])
    theta = np.asarray(report["refined"]["theta"])
    refined = NARX(terms, theta, np.zeros((len(terms), len(terms))))
    assert [(t["path"], t["samples"]) for t in report["tests"]] == [
        ("v1.csv", [0, 6000]),
        ("v2.csv", [0, 6000]),
    ]
    for test, name in zip(report["tests"], ("v1", "v2"), strict=True):
        assert test["before"]["free_run_rms"] == pytest.approx(
            free_run_rms(both, simulated_records, name), rel=1e-9
        )
        assert test["after"]["free_run_rms"] == pytest.approx(
            free_run_rms(refined, simulated_records, name), rel=1e-9
        )
        assert test["after"]["one_step_rms"] <= test["before"]["one_step_rms"] / 2
        # Judged against the records fitted, both whole: as strong a force, within their range.
        shares = coverage(
            [signals(simulated_records, "e1"), signals(simulated_records, "e2")],
            *signals(simulated_records, name),
        )
        assert test["coverage"] == asdict(shares) | {"extrapolates": False, "description": shares.describe()}
    assert report["before"] == report["tests"][0]["before"]
    assert report["effects_added"][0]["name"] == "quadratic_stiffness"
    assert {effect["decided_by"] for effect in report["effects_added"]} <= {"one-step", "simulation"}
    assert report["refined"]["estimator"] in ("least squares", "output error")
    assert report["orders_chosen"] is None

    # --validate repeated says the same; the table names each effect's criterion and each record,
    # and says which record judges the models beyond the data they were fitted on.
    table = two_record_table.stdout
    # Where stderr is not a terminal, no stages; without --unit, no unit in the report.
    assert "round 1" not in two_record_table.stderr and report["data"]["unit"] is None
    assert "1. quadratic_stiffness" in table and "decided by the one-step criterion" in table
    rows = [line.split() for line in table.splitlines() if line.endswith("[0:6000]")]
    assert [row[-2] for row in rows] == ["v1.csv", "v2.csv", "loud.csv"]
    loud = coverage(
        [signals(simulated_records, "e1"), signals(simulated_records, "e2")],
        *signals(simulated_records, "loud"),
    )
    assert loud.extrapolates
    notes = [line for line in table.splitlines() if "outside the estimation data" in line]
    assert notes == [
        f"note: loud.csv lies partly outside the estimation data ({loud.describe()}): its figures judge "
        "the models where they extrapolate"
    ]
    for row, test in zip(rows[:2], report["tests"], strict=True):
        assert float(row[2]) == pytest.approx(test["before"]["free_run_rms"], rel=1e-3)
        assert float(row[3]) == pytest.approx(test["after"]["free_run_rms"], rel=1e-3)


def side_by_side(folder: Path, names: list[str], path: Path) -> None:
    """The named records in one CSV, as the Wiener–Hammerstein benchmark publishes its
    realisations: a group of columns ``"u",,…`` of their x, one ``"y",,…`` of their y, and fs."""
    records = [read_record(folder / f"{name}.csv") for name in names]
    padding = "," * (len(names) - 1)
    columns = np.column_stack([*(r.x for r in records), *(r.y for r in records)])
    rows = [",".join(f"{value:.17g}" for value in row) + "," for row in columns]
    rows[0] += f"{records[0].fs:g}"
    path.write_text("\n".join([f'"u"{padding},"y"{padding},"fs"', *rows]) + "\n")


def test_the_realisations_of_one_file_are_records_as_separate_files_are(
    simulated_records: Path, two_record_report: dict
):
    side_by_side(simulated_records, ["e1", "e2"], simulated_records / "estimation.csv")
    side_by_side(simulated_records, ["v1", "v2"], simulated_records / "test.csv")
    grouped = refine_report(
        "estimation.csv", "--x", "u", "--y", "y", "--declared", "2dof",
        "--validate", "test.csv", "--jobs", "1", cwd=simulated_records
    )  # fmt: skip
    separate = two_record_report
    assert grouped["data"]["estimation"] == [
        {"path": "estimation.csv", "x": "u1", "y": "y1", "samples": [0, 6000]},
        {"path": "estimation.csv", "x": "u2", "y": "y2", "samples": [0, 6000]},
    ]
    assert [(t["path"], t["x"], t["y"]) for t in grouped["tests"]] == [
        ("test.csv", "u1", "y1"),
        ("test.csv", "u2", "y2"),
    ]
    sources = ("path", "x", "y")
    for key in ("declared", "refined", "effects_added", "check_free_run_rms"):
        assert grouped[key] == separate[key], key
    for one, other in zip(grouped["tests"], separate["tests"], strict=True):
        assert {k: v for k, v in one.items() if k not in sources} == {
            k: v for k, v in other.items() if k not in sources
        }


def test_each_effect_added_carries_its_coefficients_and_shares_of_the_first_record_judged(
    simulated_records: Path, two_record_report: dict
):
    """The JSON report's ``contribution`` of each effect (models.explanation), computed here
    from the refined model the report holds, on v1, the first record judged, along its free run."""
    report = two_record_report
    refined = report["refined"]
    model = NARX(
        parse_terms(refined["terms"]), np.array(refined["theta"]), np.zeros((len(refined["theta"]),) * 2)
    )
    x, y = signals(simulated_records, "v1")
    run = model.simulate(x, y)
    regressors, _ = regressor_matrix(model.terms, x, run)
    scale = np.sqrt(np.mean(y[model.max_lag :] ** 2))
    assert report["explanation"]["along"] == "free run"
    assert report["explanation"]["output_rms"] == pytest.approx(scale)
    assert report["effects_added"], "the quadratic spring is found"
    claimed = []
    for effect in report["effects_added"]:
        contribution = effect["contribution"]
        assert contribution["terms"] == effect["terms"]
        columns = [refined["terms"].index(term) for term in effect["terms"]]
        claimed += columns
        assert contribution["coefficients"] == [refined["theta"][i] for i in columns]
        assert all(error > 0 for error in contribution["standard_errors"])
        part = regressors[:, columns] @ model.theta[columns]
        assert contribution["share"] == pytest.approx(np.sqrt(np.mean(part**2)) / scale, rel=1e-9)
        theta = model.theta.copy()
        theta[columns] = 0.0
        without = NARX(model.terms, theta, model.covariance).simulate(x, y)[model.max_lag :]
        if np.all(np.abs(without) <= RESTLESS * np.max(np.abs(y[model.max_lag :]))):
            moved = np.sqrt(np.mean((without - run[model.max_lag :]) ** 2)) / scale
            assert contribution["removal_share"] == pytest.approx(moved, rel=1e-9)
        else:  # the run without the effect leaves every bound (or is not finite)
            assert contribution["diverges_without"] and contribution["removal_share"] is None
    # The declared structure's terms carry the output: the rig is a linear structure with a
    # small nonlinearity, and its free run follows the measured output closely.
    declared = report["explanation"]["declared"]
    assert declared["terms"] == [t for i, t in enumerate(refined["terms"]) if i not in claimed]
    assert declared["share"] == pytest.approx(1.0, abs=0.1)


def test_the_table_prints_each_effects_shares_and_coefficients_under_it(
    two_record_report: dict, two_record_table: subprocess.CompletedProcess[str]
):
    report, table = two_record_report, two_record_table.stdout
    assert report["effects_added"]
    assert (
        f"under each effect, shares of the output's RMS ({report['explanation']['output_rms']:.4g} "
        f"{MATHTEXT_UNIT}) on "
        "v1.csv [0:6000]: of each step" in table
    )
    lines = table.splitlines()
    for number, effect in enumerate(report["effects_added"], start=1):
        (at,) = [i for i, line in enumerate(lines) if line.startswith(f"{number}. {effect['name']} (")]
        contribution = effect["contribution"]
        without = (
            "the free run diverges without it"
            if contribution["diverges_without"]
            else f"without it the free run moves {100 * contribution['removal_share']:.3g} %"
        )
        term, value, error = (contribution[key][0] for key in ("terms", "coefficients", "standard_errors"))
        share = f"{100 * contribution['share']:.3g} %"
        assert lines[at + 1].startswith(
            f"   of each step {share}; {without}: {term} = {value:.4g} ± {error:.2g}"
        ), lines[at + 1]


def test_the_figure_draws_each_effects_contribution_and_shares(simulated_records: Path):
    x, y = signals(simulated_records, "e1")
    refined = refine_record(x, y, EXACT_TERMS, [(0, 4000)], (4000, 6000), fs=1500.0)
    explanation = explain_refinement(refined.refinement, x[4000:], y[4000:], 0, 4000)
    names = [effect.name for effect in refined.refinement.effects_added]
    assert names, "the quadratic spring is found"
    figure = draw_refinement_figure(refined, x[4000:], y[4000:], 0, 1500.0, "y", "m", explanation)
    _, _, run, steps, shares = figure.axes
    assert [line.get_label() for line in steps.get_lines()[: len(names)]] == names
    assert steps.get_ylabel() == "added to each step of y [m]"
    # Over the free run's shown stretch: the same samples as the panel above.
    assert steps.get_lines()[0].get_xdata()[[0, -1]] == pytest.approx(run.get_lines()[0].get_xdata()[[0, -1]])
    # One row of bars an effect, the first on top.
    assert [label.get_text() for label in shares.get_yticklabels()] == names
    assert list(shares.get_yticks()) == list(range(len(names)))[::-1]
    assert "m)" in shares.get_title()
    plt.close(figure)
    # Without an explanation, the three panels as before.
    figure = draw_refinement_figure(refined, x[4000:], y[4000:], 0, 1500.0)
    assert len(figure.axes) == 3
    plt.close(figure)


def test_records_are_fitted_through_the_transient_and_judged_after_it(clean_records: Path):
    report = refine_report(
        "e1.csv", "e2.csv", "--declared", "2dof", "--validate", "v1.csv", "--transient", "1000",
        "--initial", "20", "--jobs", "1", cwd=clean_records
    )  # fmt: skip
    assert report["data"]["transient"] == 1000 and report["data"]["initial"] == 20
    assert [e["samples"] for e in report["data"]["estimation"]] == [[0, 6000], [0, 6000]]
    fitted = declared_fit(clean_records, ["e1", "e2"])
    np.testing.assert_allclose(report["declared"]["theta"], fitted.theta, rtol=1e-9)
    (test,) = report["tests"]
    assert test["samples"] == [1000, 6000]
    # The free run starts from v1's first 20 measured outputs, as the record does, and runs
    # through the transient; the samples after it are scored.
    record = read_record(clean_records / "v1.csv")
    start = 20 - fitted.max_lag
    simulated = fitted.simulate(record.x[start:], record.y[start:])
    expected = float(np.sqrt(np.mean((simulated[1000 - start :] - record.y[1000:]) ** 2)))
    assert test["before"]["free_run_rms"] == pytest.approx(expected, rel=1e-9)


def test_parts_of_one_record_count_after_its_transient_and_are_reported_as_the_file_numbers_them(
    clean_records: Path,
):
    report = refine_report(
        "e1.csv", "--declared", "2dof", "--transient", "1000", "--estimation", "0:3000",
        "--test", "3000:5000", "--jobs", "1", cwd=clean_records
    )  # fmt: skip
    assert [e["samples"] for e in report["data"]["estimation"]] == [[1000, 4000]]
    assert [t["samples"] for t in report["tests"]] == [[4000, 6000]]
    record = read_record(clean_records / "e1.csv")
    fitted = fit_narx([(record.x[1000:4000], record.y[1000:4000])], EXACT_TERMS)
    np.testing.assert_allclose(report["declared"]["theta"], fitted.theta, rtol=1e-9)


def test_estimation_parts_leave_out_a_glitch_between_them(clean_records: Path, tmp_path: Path):
    # One sample of y at ten times the record's largest, as a sensor's glitch leaves: least squares
    # over a part holding it is pulled far from the fit without it.
    record = read_record(clean_records / "e1.csv")
    glitched = record.y.copy()
    glitched[2000] = 10 * np.abs(record.y).max()
    (tmp_path / "glitched.csv").write_text(dump_csv(record.x, glitched, record.fs))
    split = ("--declared", "2dof", "--jobs", "1", "--test", "4000:6000", "--estimation")
    whole = refine_report("glitched.csv", *split, "0:4000", cwd=tmp_path)
    parts = refine_report("glitched.csv", *split, "0:1990,2010:4000", cwd=tmp_path)
    assert [e["samples"] for e in parts["data"]["estimation"]] == [[0, 1990], [2010, 4000]]
    # The parts are fitted as records of their own: no lag reaches across the gap into the glitch.
    # (That they then refine as the record without the glitch is tests/test_refinement_protocol.py's.)
    apart = fit_narx([(record.x[a:b], record.y[a:b]) for a, b in ((0, 1990), (2010, 4000))], EXACT_TERMS)
    np.testing.assert_allclose(parts["declared"]["theta"], apart.theta, rtol=1e-9)
    without_glitch = fit_narx([(record.x[:4000], record.y[:4000])], EXACT_TERMS)
    assert not np.allclose(whole["declared"]["theta"], without_glitch.theta, rtol=1e-2)
    # Fitted across the glitch, the declared model's one-step error on the test part is thousands of
    # times larger, and its free run there diverges (the report's None).
    (across,), (around,) = whole["tests"], parts["tests"]
    assert around["before"]["one_step_rms"] < across["before"]["one_step_rms"] / 1000
    assert across["before"]["free_run_rms"] is None and around["before"]["free_run_rms"] is not None
    # The report fitted across the glitch names it by its sample in the record; around it, none.
    (note,) = [note for note in whole["notes"] if "as a glitch does" in note]
    assert note.startswith(f"y[2000] = {glitched[2000]:.4g} lies more than 6 times as far")
    assert note.endswith("if it is one, leave it out with estimation parts around it")
    assert not [note for note in parts["notes"] if "glitch" in note]
    refused = invoke("refine", "glitched.csv", *split, "0:3000,2000:4000", cwd=tmp_path, check=False)
    assert refused.returncode == 2 and "2000:4000 starts before 0:3000 ends" in refused.stderr
    waves = ("--declared", "y[t-1],x[t-1],sin(2pi*0.01*t)", "--estimation", "0:1990,2010:4000")
    refused = invoke("refine", "glitched.csv", *waves, cwd=tmp_path, check=False)
    assert refused.returncode == 2 and "sinusoid of time is fitted on one stretch" in refused.stderr


def test_a_glitch_in_one_of_several_records_is_named_by_its_file(clean_records: Path, tmp_path: Path):
    # Their first 2500 samples: the loop's length is not what is checked.
    for name in ("e1", "e2", "v1"):
        record = read_record(clean_records / f"{name}.csv")
        x = record.x[:2500].copy()
        if name == "e2":
            x[777] = 10 * np.abs(x).max()
            glitch = x[777]
        (tmp_path / f"{name}.csv").write_text(dump_csv(x, record.y[:2500], record.fs))
    declared = ("--declared", "2dof", "--jobs", "1")
    result = invoke("refine", "e1.csv", "e2.csv", "--validate", "v1.csv", *declared, cwd=tmp_path)
    assert f"note: x[777] of e2.csv = {glitch:.4g} lies more than 6 times as far" in result.stdout
    assert "median input" in result.stdout and "y[" not in result.stdout.split("note: x[777]")[1]


def test_a_unit_is_plotted_as_the_text_given(
    simulated_records: Path, two_record_table: subprocess.CompletedProcess[str]
):
    assert f"free-run RMS [{MATHTEXT_UNIT}]" in two_record_table.stdout
    assert (simulated_records / "two-records.png").read_bytes().startswith(PNG_MAGIC)


def test_the_plot_is_in_hz_from_the_files_times_and_per_sample_without_a_rate(
    clean_records: Path, tmp_path: Path
):
    """A CSV stating no rate but holding a column of times (written to six digits, as loggers
    do): refine takes the rate from it, and the figure's residual spectrum runs in Hz up to the
    Nyquist frequency and its free run over seconds. The same record with neither: in cycles per
    sample up to 0.5, over samples."""
    record = read_record(clean_records / "e1.csv")
    n, fs = len(record.y), record.fs
    rows = zip(np.arange(n) / fs, record.x, record.y, strict=True)
    (tmp_path / "timed.csv").write_text(
        "Time,x,y\n" + "".join(f"{t:.6g},{a:.17g},{b:.17g}\n" for t, a, b in rows)
    )
    (tmp_path / "bare.csv").write_text(dump_csv(record.x, record.y, fs).split("\n", 1)[1])  # no '# fs='
    report = refine_report("timed.csv", "--declared", "2dof", "--jobs", "1", cwd=tmp_path)
    # Six digits over the record's 4 s: its span, and so the rate, known to a few parts in 10⁶.
    assert report["data"]["fs"] == pytest.approx(fs, rel=2e-6)
    test = (2 * n // 3, n)
    for name, nyquist, frequency, along in (
        ("timed", report["data"]["fs"] / 2, "Hz", "time [s]"),
        ("bare", 0.5, "cycles/sample", "sample"),
    ):
        read = read_record(tmp_path / f"{name}.csv", signal_layout(None, None))
        refined = refine_record(read.x, read.y, EXACT_TERMS, [(0, test[0])], test, fs=read.fs)
        figure = draw_refinement_figure(refined, read.x[slice(*test)], read.y[slice(*test)], 0, read.fs)
        _, spectrum, run = figure.axes
        assert spectrum.get_xlabel() == f"frequency [{frequency}]"
        assert spectrum.get_xlim() == pytest.approx((0.0, nyquist))
        drawn = max(line.get_xdata()[-1] for line in spectrum.get_lines())
        assert drawn == pytest.approx(nyquist, rel=1e-7)
        last = run.get_lines()[0].get_xdata()[-1]  # the test part's last sample
        assert run.get_xlabel() == along and last == pytest.approx((n - test[0] - 1) / (read.fs or 1.0))
        plt.close(figure)


def test_a_column_of_times_that_does_not_step_uniformly_gives_no_rate(tmp_path: Path):
    """Times with a gap (a record spliced from two) are refused, saying how to state the rate."""
    t = np.r_[np.arange(100), np.arange(150, 250)] / 1500
    (tmp_path / "gap.csv").write_text(
        "t,x,y\n" + "".join(f"{value:.17g},{k},{-k}\n" for k, value in enumerate(t))
    )
    result = invoke("refine", "gap.csv", "--declared", "2dof", cwd=tmp_path, check=False)
    assert result.returncode == 2
    assert (
        "the column 't' does not step uniformly forward" in result.stderr
        and "'# fs=' or --fs" in result.stderr
    )


def test_two_jobs_run_on_one_cpu_to_the_report_of_one_and_more_than_two_a_cpu_are_refused(
    simulated_records: Path, two_record_report: dict
):
    """The candidates of each round built, and the structures judged on the check blocks (each
    round's families, the simulation error's prefixes), in two processes (the effects' finders
    and combiners sent to them) or in this one: the same effects, parameters and figures, to the
    last digit. The two processes run on a machine of one CPU (the command pinned to one), where
    they were refused as more processes than CPUs; twice the CPUs is the most. (The linear orders
    chosen in processes when nothing is declared: the models' test,
    tests/test_refinement.py's ``test_linear_orders_chosen_in_processes_are_chosen_as_in_this_one``.)"""
    one_cpu = min(os.sched_getaffinity(0))
    pinned = subprocess.run(
        [NARXWATCH, "refine", *TWO_RECORDS, "--json", "--jobs", "2"], cwd=simulated_records,
        capture_output=True, text=True, timeout=300,
        preexec_fn=lambda: os.sched_setaffinity(0, {one_cpu}),
    )  # fmt: skip
    assert pinned.returncode == 0, pinned.stderr
    assert json.loads(pinned.stdout) == two_record_report
    assert two_record_report["effects_added"]  # the loop did find something to add
    # Three are refused before any work: the command in this process, this thread pinned as it was.
    allowed = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {one_cpu})
    try:
        refused = invoke("refine", *TWO_RECORDS, "--json", "--jobs", "3", cwd=simulated_records, check=False)
    finally:
        os.sched_setaffinity(0, allowed)
    assert refused.returncode == 2 and refused.stdout == ""
    assert "at most 2, twice the CPUs this command may use; got 3" in " ".join(refused.stderr.split())


# prctl(2)'s option: the orphans of this process's descendants become its children.
PR_SET_CHILD_SUBREAPER = 36


@contextlib.contextmanager
def adopting_orphans() -> Iterator[None]:
    """This process the parent of its descendants' orphans while the block runs (Linux's child
    subreaper): it can then wait for them and see how they ended."""
    libc = ctypes.CDLL(None, use_errno=True)
    assert libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0, os.strerror(ctypes.get_errno())
    try:
        yield
    finally:
        libc.prctl(PR_SET_CHILD_SUBREAPER, 0, 0, 0, 0)


def end_of(pid: int, timeout: float) -> int:
    """The wait status of ``pid``, a child of this process (adopted: :func:`adopting_orphans`);
    a process still running after ``timeout`` seconds is killed and the test fails."""
    deadline = time.monotonic() + timeout
    while (ended := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail(f"worker {pid} outlived its command by {timeout} s")
        time.sleep(0.01)
    return ended[1]


@pytest.mark.parametrize(
    ("stop", "group", "code", "seen"),
    [
        (signal.SIGINT, True, 130, 2),  # a terminal's Ctrl-C: the command's whole process group
        (signal.SIGINT, True, 130, 1),  # the same as its workers are being forked
        (signal.SIGTERM, False, -signal.SIGTERM, 2),  # timeout, a service manager: the command alone
        (signal.SIGKILL, False, -signal.SIGKILL, 2),  # killed outright
    ],
    ids=["ctrl-c", "ctrl-c-as-the-workers-start", "sigterm", "sigkill"],
)
def test_a_stopped_command_leaves_no_worker_behind_and_prints_no_traceback(
    silverbox_dir, tmp_path, stop, group, code, seen
):
    """However ``refine`` is stopped, its worker processes end with it, and none prints a traceback
    (each used to on Ctrl-C; after SIGTERM or SIGKILL they waited for work for ever, then looked
    for their command once a second: now they are killed as it ends). Stopped
    when ``seen`` of its workers are running: both (the loop has reached its first round), or the
    first (the pool is starting: a Ctrl-C there used to leave the command waiting at its exit for
    workers nobody had told to stop, or a worker's traceback)."""
    assert NARXWATCH, "the narxwatch console script is not installed next to this Python"
    command = [
        NARXWATCH, "refine", str(silverbox_dir / "SNLS80mV.csv"), "--format", "silverbox",
        "--declared", "linear:4,4", "--jobs", "2",
    ]  # fmt: skip
    started = subprocess.Popen(
        command, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job has
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    children = Path(f"/proc/{started.pid}/task/{started.pid}/children")
    deadline = time.monotonic() + 60
    while len(children.read_text().split()) < seen:
        assert time.monotonic() < deadline and started.poll() is None, "no worker processes started"
        time.sleep(0.05 if seen > 1 else 0.001)
    workers = [int(pid) for pid in children.read_text().split()]
    if group:
        os.killpg(started.pid, stop)
    else:
        # The command alone, which leaves its workers orphans: adopted here, their ends are seen.
        with adopting_orphans():
            os.kill(started.pid, stop)
            started.wait(timeout=30)
            ends = [end_of(pid, timeout=10) for pid in workers]
        # Killed as the command ended, not left to find out later that it had.
        assert all(os.WIFSIGNALED(end) and os.WTERMSIG(end) == signal.SIGKILL for end in ends), ends
    with contextlib.suppress(subprocess.TimeoutExpired):  # a leftover worker holds the pipes open
        started.communicate(timeout=10)
    deadline = time.monotonic() + 5
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [pid for pid in workers if Path(f"/proc/{pid}").exists()]
    with contextlib.suppress(ProcessLookupError):  # a leftover would outlive the test run otherwise
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    assert not left, f"workers {left} outlived the command"
    _, stderr = started.communicate(timeout=10)
    assert started.returncode == code
    assert "Traceback" not in stderr and "KeyboardInterrupt" not in stderr, stderr


def test_records_at_different_rates_are_refused_naming_each(simulated_records: Path, tmp_path: Path):
    text = (simulated_records / "v1.csv").read_text()
    assert text.startswith("# fs=1500")
    (tmp_path / "slow.csv").write_text(text.replace("# fs=1500", "# fs=1000", 1))
    figure = tmp_path / "refine.png"
    result = invoke(
        "refine", str(simulated_records / "e1.csv"), "--declared", "2dof",
        "--validate", str(tmp_path / "slow.csv"), "--plot", str(figure), cwd=tmp_path, check=False,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    message = " ".join(result.stderr.split())
    assert "e1.csv at 1500 Hz" in message and "slow.csv at 1000 Hz" in message
    assert "resample them to one rate" in message
    assert result.stdout == "" and not figure.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["e1.csv", "e2.csv"], "name the records to judge on: --validate"),
        (
            ["e1.csv", "e2.csv", "--validate", "v1.csv", "--estimation", "0:3000"],
            "picks a part of one record",
        ),
        (
            ["e1.csv", "--validate", "v1.csv", "--transient", "6000"],
            "e1.csv: --transient 6000 leaves nothing of its 6000 samples",
        ),
        (["e1.csv", "--validate", "v1.csv", "--transient", "-1"], "--transient must be 0 or more"),
    ],
)
def test_bad_record_protocols_are_refused(simulated_records: Path, args, message):
    result = invoke("refine", *args, "--declared", "2dof", cwd=simulated_records, check=False)
    assert result.returncode == 2 and message in " ".join(result.stderr.split()), result.stderr
    assert result.stdout == ""


def test_records_that_repeat_their_excitation_report_the_noise_between_periods(tmp_path: Path):
    """Three records of four periods of a multisine through a second-order system, with white
    output noise 0.3: the right linear model's check figure is at the noise floor, and the
    table says so, with the floor's figure and its standard error. (Its JSON fields are the
    report's, which the refinement routes give: tests/test_dashboard_browser.py.)"""
    for seed, name in enumerate(("e1", "e2", "e3"), start=31):
        x, _, y = measured(periods=4, sigma=0.3, seed=seed)
        np.savetxt(
            tmp_path / f"{name}.csv", np.column_stack([x, y]), delimiter=",", header="x,y", comments=""
        )
    args = ("refine", "e1.csv", "e2.csv", "--declared", "linear:2,2", "--validate", "e3.csv", "--jobs", "1")
    printed = invoke(*args, cwd=tmp_path).stdout
    assert "noise between the checked records' periods (6 of 512 samples)" in printed, printed
    assert "the check figure is at that floor" in printed, printed
    floor = re.search(r"which no model can simulate, is (\S+) ± (\S+):", printed)
    assert floor, printed
    assert abs(float(floor[1]) - 0.3) < 3 * float(floor[2])


def test_nothing_declared_starts_from_chosen_orders_and_prints_what_the_tails_withdrew(tmp_path):
    """Nothing declared, a short record whose steps grow (harness.extrapolating; the loop's
    choices on it are tests/test_refinement.py's): the table names the linear orders the loop
    chose and starts from them, says which effects were withdrawn and why, both free runs over
    the held-out tails (seen by the choice of the orders alone), the uncertainty the gain had to
    exceed, and the best effect tried. The table is printed from the JSON report's
    "orders_chosen" and "declared" (one loop, not two)."""
    x, y = growing_steps(750, seed=3)
    (tmp_path / "record.csv").write_text(dump_csv(x, y, 100.0))
    table = invoke("refine", "record.csv", "--jobs", "1", cwd=tmp_path).stdout
    chosen = re.search(r"the loop chose the linear model ny = (\d+), nx = (\d+), input delay (\d)", table)
    assert chosen, table
    ny, nx, delay = (int(group) for group in chosen.groups())
    assert 1 <= ny <= 10 and nx == ny and delay in (0, 1)
    lags = [f"y[t-{k}]" for k in range(1, ny + 1)] + [f"x[t-{k}]" for k in range(delay, delay + nx)]
    # The steps' even part drives the output's mean off zero: the start may carry a constant.
    declared = ", ".join(lags).replace("x[t-0]", "x[t]")
    assert f"declared: {declared}\n" in table or f"declared: {declared}, 1\n" in table, table
    (line,) = [line for line in table.splitlines() if line.startswith("held-out tails")]
    best = re.search(r"the start is returned \(the best effect tried: (\w+)\)$", line)
    assert best, line
    assert f"withdrawn: {best[1]}" in table and "not better than the start on the held-out tails" in table
    assert "(100 samples no choice but the linear orders saw)" in line, line
    assert re.search(r"start \S+, refined \S+;", line), line
    assert re.search(r"gain \S+% of the mean square, threshold \S+% \(its uncertainty at level 0.05\)", line)
    assert "note: the data could not support the effects" in table


def test_a_test_part_beyond_the_refined_models_amplitude_range_is_said_to_diverge_for_that(tmp_path):
    """Nothing declared, the short record whose steps grow on which the kept polynomial escapes
    over the test part (tests/test_refinement.py): the table prints both models' amplitude
    ranges, the linear start's without limit and the refined model's up to a scale the test
    part's input passes, and its note on the diverged test part names that range as the reason."""
    x, y = growing_steps(750, seed=2)
    (tmp_path / "record.csv").write_text(dump_csv(x, y, 100.0))
    table = invoke("refine", "record.csv", "--jobs", "1", cwd=tmp_path).stdout
    (line,) = [line for line in table.splitlines() if line.startswith("amplitude range")]
    assert "estimation inputs scaled by 1, 1.25, 1.5, 2, 3" in line, line
    assert "the linear start bounded for inputs of any amplitude" in line, line
    limit = re.search(
        r"the refined model bounded for inputs up to (\S+)× the estimation records' amplitude", line
    )
    assert limit, line
    scale = np.max(np.abs(x[500:])) / np.max(np.abs(x[:500]))
    assert float(limit[1]) < scale
    (note,) = [line for line in table.splitlines() if "the refined model's free run diverged" in line]
    assert note.startswith("note: on record.csv"), note
    assert f"its input reaches {scale:.2g}× the estimation records' largest" in note, note
    assert f"up to {limit[1]}× the estimation records' amplitude" in note, note
