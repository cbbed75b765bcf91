"""The ``narxwatch`` command line, run as a user runs it: the installed console script.

Each command's work is run through the script once (:func:`run`: simulate, train, inspect,
reproduce); its other runs, the tables of refusals, the help texts and the records a fixture needs
go through its entry point in the test's process (:func:`invoke`), the same code but for the
second of imports a new process spends.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import MODE_FIELDS, VERDICT_FIELDS

from harness.cli import PNG_MAGIC, invoke, run
from simulator.theory import EXACT_TERMS


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """Healthy and k2 experiment records, a manifest, and trained models, made with the CLI."""
    path = tmp_path_factory.mktemp("cli")
    invoke("simulate", "--n", "30000", "--seed", "1", "--out", "healthy.csv", cwd=path)
    with (path / "manifest.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["path", "k"])
        for index, k in enumerate(range(-32, 33, 8)):
            name = f"experiments/k2_{k}.npz"
            invoke(
                "simulate", "--fault", "k2", "--k", str(k), "--seed", str(10 + index), "--out", name, cwd=path
            )
            writer.writerow([name, k])
    invoke("train", "baseline", "healthy.csv", "--terms", "2dof", "--out", "baseline.json", cwd=path)
    invoke(
        "train", "fault-mode", "--name", "k2", "--experiments", "manifest.csv", "--terms", "baseline.json",
        "--out", "k2.json", cwd=path,
    )  # fmt: skip
    return path


@pytest.mark.parametrize(
    "command",
    [
        [],
        ["simulate"],
        ["train"],
        ["train", "baseline"],
        ["train", "fault-mode"],
        ["inspect"],
        ["refine"],
        ["reproduce"],
    ],
)
def test_every_command_has_help(command, tmp_path):
    result = invoke(*command, "--help", cwd=tmp_path)
    assert "Usage" in result.stdout


def test_simulate_writes_the_documented_csv(workdir):
    lines = (workdir / "healthy.csv").read_text().splitlines()
    assert lines[:2] == ["# fs=1500", "x,y"]
    assert len(lines) == 2 + 30000


def test_simulate_npz_holds_x_y_fs_and_is_reproducible(workdir, tmp_path):
    run("simulate", "--fault", "k2", "--k", "-32", "--seed", "10", "--out", "again.npz", cwd=tmp_path)
    with np.load(tmp_path / "again.npz") as again, np.load(workdir / "experiments/k2_-32.npz") as first:
        assert set(again.files) == {"x", "y", "fs"}
        assert float(again["fs"]) == 1500.0
        np.testing.assert_array_equal(again["y"], first["y"])


def test_simulate_accepts_effects_and_parameters(tmp_path):
    invoke(
        "simulate",
        "--n",
        "500",
        "--seed",
        "3",
        "--effect",
        "coulomb2=50",
        "--effect",
        "sine=500@12.5",
        "--param",
        "c1=800",
        "--noise-std",
        "1e-4",
        "--out",
        "e.csv",
        cwd=tmp_path,
    )
    plain = invoke("simulate", "--n", "500", "--seed", "3", "--out", "p.csv", cwd=tmp_path)
    assert "500 samples" in plain.stdout
    assert (tmp_path / "e.csv").read_text() != (tmp_path / "p.csv").read_text()


CHAIN = ["--masses", "3", "--mass", "10,20,15", "--stiffness", "50e3,80e3,30e3", "--damping", "2000"]
ACCELEROMETER = [*CHAIN, "--response", "acceleration", "--outputs", "1", "--excitation-std", "1000"]


def test_simulate_writes_a_chain_s_accelerometer_with_sensor_noise_a_share_of_its_rms(tmp_path):
    """A structure that is not the rig: the chain's driving-point acceleration, its sensors' noise 1 %
    of the healthy signals' RMS on x and on y, the same floor with a spring loosened."""
    quiet = [*ACCELEROMETER, "--disturbance-std", "0", "--n", "3000", "--seed", "4"]
    written = invoke("simulate", *quiet, "--out", "clean.npz", cwd=tmp_path)
    assert "3000 samples at fs = 1500 Hz" in written.stdout and "m/s²" in written.stdout
    invoke("simulate", *quiet, "--noise-share", "0.01", "--out", "noisy.npz", cwd=tmp_path)
    invoke(
        "simulate",
        *quiet,
        "--noise-share",
        "0.01",
        "--fault",
        "k2",
        "--k",
        "8",
        "--out",
        "k2.npz",
        cwd=tmp_path,
    )
    with np.load(tmp_path / "clean.npz") as clean, np.load(tmp_path / "noisy.npz") as noisy:
        assert set(noisy.files) == {"x", "y", "fs"} and float(noisy["fs"]) == 1500.0
        y_noise, x_noise = noisy["y"] - clean["y"], noisy["x"] - clean["x"]
        assert 0.009 < np.std(y_noise) / np.std(clean["y"]) < 0.011
        assert 0.009 < np.std(x_noise) / 1000.0 < 0.011
        assert abs(np.corrcoef(y_noise[1:], y_noise[:-1])[0, 1]) < 0.1  # white
    with np.load(tmp_path / "k2.npz") as faulty, np.load(tmp_path / "clean.npz") as clean:
        assert not np.allclose(faulty["y"], clean["y"], rtol=0.01)  # the spring changed the response
    # Displacement by default, every mass measured: a channel per mass.
    every = invoke("simulate", *CHAIN, "--n", "500", "--seed", "1", "--out", "all.csv", cwd=tmp_path)
    assert every.stdout.endswith(" m\n")
    assert (tmp_path / "all.csv").read_text().splitlines()[1] == "x,y1,y2,y3"


def test_a_chain_s_default_has_no_unmeasured_force_and_the_rig_keeps_the_paper_s(tmp_path):
    """Without --disturbance-std a chain, a structure of one's own, is simulated without the rig's
    unmeasured force on mass 1 (its noise is its sensors'); the rig keeps the paper's 800 N."""
    seeded = ["--n", "500", "--seed", "5"]
    for name, structure, level in (("chain", ACCELEROMETER, "0"), ("rig", [], "800")):
        invoke("simulate", *structure, *seeded, "--out", f"{name}.npz", cwd=tmp_path)
        invoke(
            "simulate",
            *structure,
            *seeded,
            "--disturbance-std",
            level,
            "--out",
            f"{name}-given.npz",
            cwd=tmp_path,
        )
        with np.load(tmp_path / f"{name}.npz") as default, np.load(tmp_path / f"{name}-given.npz") as given:
            np.testing.assert_array_equal(default["y"], given["y"], err_msg=name)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--noise-share", "0.01"], "--noise-share and --outputs are options of the chain: give --masses N"),
        ([*CHAIN, "--noise-share", "1.5"], "--noise-share must lie in [0, 1)"),
        ([*CHAIN, "--noise-share", "0.01", "--noise-std", "1e-3"], "give it or --noise-std/--x-noise-std"),
        (
            [*CHAIN, "--response", "velocity"],
            "--response 'velocity': choose one of displacement, acceleration",
        ),
        ([*CHAIN, "--fault", "k5"], "k5"),
        ([*CHAIN, "--outputs", "4"], "--outputs must name distinct masses of the chain, 1 … 3"),
        ([*CHAIN, "--param", "c1=800"], "--effect and --param act on the 2-DOF rig"),
        (["--stiffness", "1e4"], "--stiffness: options of the chain, which needs its number of masses"),
        (["--effect", "gremlins=3"], "cannot read effect"),
        (["--effect", "coulomb1=lots"], "not a number"),
        (["--param", "m3=4"], "unknown parameter m3"),
        (["--param", "m1"], "NAME=NUMBER"),
        (["--fault", "k9"], "unknown fault mode"),
        (["--out", "r.txt"], "unknown record format"),
        (["--excitation-std", "1e7"], "diverged"),
        (
            [
                "--param",
                "m1=1",
                "--param",
                "m2=5.5",
                "--param",
                "k1=1000",
                "--param",
                "k2=9000",
                "--param",
                "c1=7.5",
                "--param",
                "c2=3",
            ],
            "unstable",
        ),
    ],
)
def test_simulate_refuses_bad_input_with_a_message(tmp_path, args, message):
    base = ["simulate", "--n", "2000", "--seed", "1"]
    out = [] if "--out" in args else ["--out", "r.csv"]
    result = invoke(*base, *out, *args, cwd=tmp_path, check=False)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "r.csv").exists()


def test_trained_models_are_documents_with_metadata(workdir):
    baseline = json.loads((workdir / "baseline.json").read_text())
    assert baseline["kind"] == "narx" and len(baseline["terms"]) == 8
    assert baseline["metadata"]["fs"] == 1500.0
    k2 = json.loads((workdir / "k2.json").read_text())
    assert k2["kind"] == "fnarx" and k2["name"] == "k2"
    assert k2["basis"] == {"family": "chebyshev2", "size": 2, "k_min": -32.0, "k_max": 32.0}
    assert len(k2["metadata"]["experiments"]) == 9


def test_train_with_explicit_terms(workdir, tmp_path):
    run(
        "train",
        "baseline",
        str(workdir / "healthy.csv"),
        "--terms",
        "y[t-1],y[t-2],x[t-4]",
        "--out",
        "linear.json",
        cwd=tmp_path,
    )
    assert json.loads((tmp_path / "linear.json").read_text())["terms"] == ["y[t-1]", "y[t-2]", "x[t-4]"]


def test_train_without_terms_chooses_a_baseline_and_a_fault_mode_asks_for_them(workdir, tmp_path):
    """No command assumes the paper rig's terms: a baseline without --terms has them chosen from
    its records (on the rig's: fourth order or more, its input a sample late) and says what it
    chose; a fault mode needs --terms, which its baseline's model file gives. The choice is made
    on a record of 4000 samples, as tests/test_baseline_choice.py makes it (the workdir's 30 000
    add nothing to what the command is tested for but the choice's time)."""
    invoke("simulate", "--n", "4000", "--seed", "1", "--out", "healthy.csv", cwd=tmp_path)
    result = invoke("train", "baseline", "healthy.csv", "--out", "chosen.json", cwd=tmp_path)
    choice = json.loads((tmp_path / "chosen.json").read_text())["metadata"]["choice"]
    assert choice["delay"] == 1 and choice["orders"]["ny"] >= 4
    assert choice["held_out"]["free_run_nrmse"] < 0.2
    assert (
        f"terms chosen: ARX({choice['orders']['ny']}, {choice['orders']['nx']}), input delay 1"
        in result.stdout
    )
    manifest = str(workdir / "manifest.csv")
    refused = invoke("train", "fault-mode", "--name", "k2", "--experiments", manifest, "--out", "k.json",
                     cwd=workdir, check=False)  # fmt: skip
    assert refused.returncode == 2 and "--terms" in refused.stderr
    rig = json.loads((workdir / "baseline.json").read_text())
    assert rig["terms"] == [term.name for term in EXACT_TERMS]  # --terms 2dof, by name


def test_inspect_json_verdict_of_a_k2_fault(workdir):
    invoke("simulate", "--fault", "k2", "--k", "12", "--seed", "99", "--out", "record.csv", cwd=workdir)
    result = run("inspect", "record.csv", "--fault-mode", "k2.json", "--json", cwd=workdir)
    verdict = json.loads(result.stdout)
    assert set(VERDICT_FIELDS) <= set(verdict)
    assert verdict["status"] == "faulty" and verdict["fault_mode"] == "k2"
    # Within 5 interval half-widths: a generous statistical bound, not a fitted one.
    assert abs(verdict["k_hat"] - 12) < 5 * verdict["sigma_k"] * 1.96
    assert verdict["n_samples"] == 2000 and verdict["alpha"] == 0.05 and verdict["lags"] == 40
    mode = verdict["modes"][0]
    assert set(MODE_FIELDS) <= set(mode)


def test_inspect_table_output(workdir):
    invoke("simulate", "--seed", "5", "--out", "healthy_record.csv", cwd=workdir)
    result = invoke("inspect", "healthy_record.csv", "--fault-mode", "k2.json", cwd=workdir)
    assert "k2" in result.stdout and "Q crit" in result.stdout


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("x,y\n1,2\nfoo,3\n", "line 3"),
        ("x,y\n" + "1,2\n" * 10, "too short"),
        ("x,y\n" + "\n".join(f"{i},{'nan' if i == 7 else i % 5}" for i in range(300)), "NaN"),
    ],
)
def test_inspect_refuses_bad_records(workdir, content, message):
    (workdir / "bad.csv").write_text(content)
    result = invoke("inspect", "bad.csv", "--fault-mode", "k2.json", cwd=workdir, check=False)
    assert result.returncode == 2
    assert message in result.stderr


def test_inspect_refuses_a_model_of_another_sampling_rate(workdir):
    record = np.load(workdir / "experiments/k2_0.npz")
    np.savez(workdir / "fast.npz", x=record["x"], y=record["y"], fs=3000.0)
    result = invoke("inspect", "fast.npz", "--fault-mode", "k2.json", cwd=workdir, check=False)
    assert result.returncode == 2 and "3000 Hz" in result.stderr


def test_inspect_refuses_unreadable_model_files(workdir):
    (workdir / "junk.json").write_text("{not json")
    result = invoke("inspect", "healthy.csv", "--fault-mode", "junk.json", cwd=workdir, check=False)
    assert result.returncode == 2 and "not valid JSON" in result.stderr
    result = invoke("inspect", "healthy.csv", "--fault-mode", "baseline.json", cwd=workdir, check=False)
    assert result.returncode == 2 and "not a fnarx model document" in result.stderr


def test_train_fault_mode_refuses_a_bad_manifest(workdir):
    (workdir / "bad_manifest.csv").write_text("file,magnitude\na.csv,1\n")
    result = invoke(
        "train",
        "fault-mode",
        "--name",
        "k2",
        "--experiments",
        "bad_manifest.csv",
        "--terms",
        "2dof",
        "--out",
        "x.json",
        cwd=workdir,
        check=False,
    )
    assert result.returncode == 2 and "path,k" in result.stderr


def test_reproduce_writes_results_and_figures(tmp_path):
    run("reproduce", "--runs", "2", "--monte-carlo", "10", "--out", "study", cwd=tmp_path)
    results = json.loads((tmp_path / "study/results.json").read_text())
    assert set(results["cases"]) == {"I", "II", "III", "IV"}
    for case in results["cases"].values():
        for key in (
            "true_k",
            "k_hat",
            "sigma_k",
            "q",
            "mean_k_hat",
            "mean_sigma_k",
            "detected",
            "accepted_k2",
        ):
            assert key in case
        assert len(case["k_hat"]) == len(case["q"]) == 2
    assert results["settings"]["runs"] == 2 and results["monte_carlo"]["records"] == 10
    for name in ("figure3_prediction", "figure4_trajectories", "figure5_estimates", "figure6_q_statistic"):
        data = (tmp_path / f"study/{name}.png").read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 20_000
