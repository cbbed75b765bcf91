"""``--x`` and ``--y`` on the commands that read records: CSV columns and MAT variables by name,
read as the same record as the ``x,y`` file, and a bad name refused with what to fix."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from harness.api_helpers import simulated
from harness.cli import invoke
from models.narx import fit_narx
from models.terms import parse_terms
from recordfiles.writer import write_record

TERMS = "y[t-1],y[t-2],x[t-1],x[t-2]"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    """One simulated record as ``x,y`` CSV, as a CSV with a group ``"Force","Acc",,"Fs",`` (y in
    Acc2), and as a MAT file with Force (1×N), Acc (2×N) and Fs."""
    folder = tmp_path_factory.mktemp("published")
    record = simulated("none", 0.0, 41, n=4000)
    other = np.random.default_rng(5).normal(size=record.x.size)
    write_record(folder / "plain.csv", record.x, record.y, record.fs)
    rows = "".join(
        f"{a:.17g},{b:.17g},{c:.17g},{record.fs if i == 0 else ''},\n"
        for i, (a, b, c) in enumerate(zip(record.x, other, record.y, strict=True))
    )
    (folder / "named.csv").write_text('"Force","Acc",,"Fs",\n' + rows)
    scipy.io.savemat(
        folder / "named.mat", {"Force": record.x, "Acc": np.stack([other, record.y]), "Fs": record.fs}
    )
    # Acc2 one sample short, and a cell that is not a number.
    lines = (folder / "named.csv").read_text().splitlines()
    last = lines[-1].split(",")
    (folder / "short.csv").write_text("\n".join([*lines[:-1], ",".join([*last[:2], "", *last[3:]])]) + "\n")
    lines[4] = lines[4].replace(lines[4].split(",")[2], "volts", 1)
    (folder / "volts.csv").write_text("\n".join(lines) + "\n")
    return folder


# The rig's own structure: the loop has little to add, and what is compared is the record read.
REFINE = ("--declared", "2dof", "--json")


@pytest.fixture(scope="module")
def plain_report(files) -> dict:
    return json.loads(invoke("refine", "plain.csv", *REFINE, cwd=files).stdout)


@pytest.mark.parametrize("name", ["named.csv", "named.mat"])
def test_refine_reads_named_signals_as_the_plain_record(files, plain_report, name):
    named = json.loads(invoke("refine", name, "--x", "Force", "--y", "Acc2", *REFINE, cwd=files).stdout)
    # The same report but for the file and signal names it quotes.
    assert without_sources(named) == without_sources(plain_report) and named["data"]["fs"] == 1500.0


def without_sources(report: dict) -> dict:
    """``report`` without the file and signal names it quotes (a copy: the fixture's report is
    shared)."""

    def unnamed(item: dict) -> dict:
        return {k: v for k, v in item.items() if k not in ("path", "x", "y")}

    data = report["data"] | {"estimation": [unnamed(item) for item in report["data"]["estimation"]]}
    tests = [unnamed(item) for item in report["tests"]]
    return report | {"data": data, "tests": tests}


def test_train_and_select_read_named_signals(files):
    record = simulated("none", 0.0, 41, n=4000)
    invoke(
        "train",
        "baseline",
        "named.mat",
        "--x",
        "Force",
        "--y",
        "Acc2",
        "--terms",
        TERMS,
        "--out",
        "m.json",
        cwd=files,
    )
    document = json.loads((files / "m.json").read_text())
    expected = fit_narx([(record.x, record.y)], parse_terms(TERMS.split(",")))
    np.testing.assert_array_equal(document["theta"], expected.theta)
    assert document["metadata"]["fs"] == 1500.0
    options = ("--degree", "1", "--ny", "2", "--nx", "2", "--n-terms", "3", "--json")
    plain = json.loads(invoke("select", "plain.csv", *options, cwd=files).stdout)
    named = json.loads(
        invoke("select", "named.csv", "--x", "Force", "--y", "Acc2", *options, cwd=files).stdout
    )
    assert named.pop("records") == ["named.csv"] and plain.pop("records") == ["plain.csv"]
    assert named == plain


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["inspect", "named.mat", "--x", "Force", "--y", "Accel", "--fault-mode", "none.json"],
            "named.mat: the MAT file has no variable 'Accel'; it holds Force (1×4000 double), "
            "Acc (2×4000 double), Fs (1×1 double)",
        ),
        (
            ["select", "named.csv", "--x", "Force", "--y", "Acceleration"],
            "named.csv: the CSV has no column 'Acceleration'; its columns are Force, Acc (2 columns, "
            "Acc1 … Acc2), Fs",
        ),
        (
            ["train", "baseline", "named.csv", "--x", "Force", "--y", "Acc3", "--out", "m.json"],
            "'Acc3' is out of range: 'Acc' holds 2 signal(s), Acc1 … Acc2",
        ),
        (
            ["refine", "short.csv", "--x", "Force", "--y", "Acc2"],
            "x ('Force') has 4000 samples but y ('Acc2') has 3999",
        ),
        (
            ["refine", "volts.csv", "--x", "Force", "--y", "Acc2"],
            "CSV line 5: 'volts' in column 'Acc2' is not a number",
        ),
        (["select", "plain.csv", "--x", "Force"], "no column 'Force'; its columns are x, y"),
        (
            ["train", "baseline", "named.csv", "--x", "Force", "--y", "Acc", "--out", "m.json"],
            "'Acc' holds 2 signals: name one of them, Acc1 … Acc2; or, to read a record from each pair",
        ),
    ],
)  # fmt: skip
def test_bad_names_are_refused_with_what_to_fix(files, args, message):
    result = invoke(*args, cwd=files, check=False)
    assert result.returncode == 2 and message in result.stderr, result.stderr


def test_a_file_of_realisations_is_read_as_its_records_by_train_and_select(tmp_path: Path):
    """Force and Acc as 2×N matrices, one realisation a row: ``--x Force --y Acc`` gives the two
    records the two separate files give, to a baseline, to a fault mode (two experiments at the
    file's k) and to a selection."""
    realisations = {k: [simulated("k2", k, [7, k + 40, i], n=3000) for i in range(2)] for k in (-16, 0, 16)}
    for k, pair in realisations.items():
        matrices = {"Force": np.stack([r.x for r in pair]), "Acc": np.stack([r.y for r in pair])}
        scipy.io.savemat(tmp_path / f"k{k}.mat", matrices | {"Fs": pair[0].fs})
        for i, record in enumerate(pair):
            write_record(tmp_path / f"k{k}_{i}.csv", record.x, record.y, record.fs)
    signals = ("--x", "Force", "--y", "Acc")
    invoke("train", "baseline", "k0.mat", *signals, "--terms", TERMS, "--out", "grouped.json", cwd=tmp_path)
    expected = fit_narx([(r.x, r.y) for r in realisations[0]], parse_terms(TERMS.split(",")))
    baseline = json.loads((tmp_path / "grouped.json").read_text())
    np.testing.assert_array_equal(baseline["theta"], expected.theta)

    (tmp_path / "grouped.csv").write_text("path,k\n" + "".join(f"k{k}.mat,{k}\n" for k in realisations))
    (tmp_path / "separate.csv").write_text(
        "path,k\n" + "".join(f"k{k}_{i}.csv,{k}\n" for k in realisations for i in range(2))
    )
    for manifest, options in (("grouped", signals), ("separate", ())):
        invoke(
            "train", "fault-mode", "--name", "k2", "--experiments", f"{manifest}.csv", "--terms", TERMS,
            *options, "--out", f"{manifest}_k2.json", cwd=tmp_path,
        )  # fmt: skip
    grouped, separate = (json.loads((tmp_path / f"{m}_k2.json").read_text()) for m in ("grouped", "separate"))
    assert grouped.pop("metadata")["experiments"] == [{"path": f"k{k}.mat", "k": k} for k in realisations]
    separate.pop("metadata")
    assert grouped == separate

    options = ("--degree", "1", "--ny", "2", "--nx", "2", "--n-terms", "3", "--json")
    from_groups = json.loads(invoke("select", "k0.mat", *signals, *options, cwd=tmp_path).stdout)
    from_files = json.loads(invoke("select", "k0_0.csv", "k0_1.csv", *options, cwd=tmp_path).stdout)
    assert from_groups.pop("records") == ["k0.mat"] and from_files.pop("records") == ["k0_0.csv", "k0_1.csv"]
    assert from_groups == from_files
