"""Record files as the benchmarks publish them (issue 14, deliverable 6): MAT files and CSVs with
named and grouped columns, one naming rule for both, and the errors that say what to fix.

The measured files are compared with an independent read (``scipy.io.loadmat``,
``numpy.genfromtxt``); hostile MAT files are built byte by byte (``mat_bombs``).
"""

from __future__ import annotations

import hashlib
import io
import re
import subprocess
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.mat_bombs import (
    compressed,
    huge_cell,
    mat_file,
    matrix,
    struct_bomb,
    struct_element,
    v73_file,
    zeros_bomb,
)
from harness.prerequisites import benchmark_data
from models.errors import InputError
from recordfiles.reader import (
    SILVERBOX,
    Layout,
    RecordTooLargeError,
    header_groups,
    parse_csv,
    parse_mat,
    parse_record_set,
    parse_silverbox,
    read_record,
    read_record_set,
    read_split_record,
)

LIMIT = 16 * 2**20  # the service's default upload limit
F16_MAT = "F16Data_SineSw_Level3.mat"
WH_EST = "WH_EstimationExample.csv"
# shared/data/README.md
F16_SHA256 = {
    "F16Data_FullMSine_Level3.csv": "0bba7686f392c0ae3e0a99a1760892bb072220b1837acf62899841d1a9895cc5",
    "F16Data_SineSw_Level3.mat": "663cb3f8650b5adb8cd40e5d4395513e559a4af129fabf631b1db645a8ff12cd",
}


@pytest.fixture(scope="module")
def f16_dir() -> Path:
    return benchmark_data("f16-gvt", *F16_SHA256, "F16Data_SineSw_Level4_Validation.mat")


@pytest.fixture(scope="module")
def wh_dir() -> Path:
    return benchmark_data("wiener-hammerstein", "WH_EstimationExample.csv", "WH_TestDataset.csv")


def peak_allocation(action: Callable[[], object]) -> int:
    """Bytes allocated at the peak while ``action`` runs (numpy reports its buffers too)."""
    tracemalloc.start()
    try:
        action()
    except InputError:
        pass
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak


# --- the published files, read as they are ------------------------------------------------------


@pytest.mark.parametrize("level", ["Level3", "Level4_Validation"])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_f16_mat_reads_force_and_each_acceleration(f16_dir, level, k):
    path = f16_dir / f"F16Data_SineSw_{level}.mat"
    if path.name in F16_SHA256:
        assert hashlib.sha256(path.read_bytes()).hexdigest() == F16_SHA256[path.name], (
            "not the published file"
        )
    record = read_record(path, Layout("Force", f"Acceleration{k}"))
    reference = scipy.io.loadmat(path)
    assert reference["Acceleration"].shape == (3, reference["Force"].size) and record.x.size > 100_000
    np.testing.assert_array_equal(record.x, reference["Force"].ravel())
    np.testing.assert_array_equal(record.y, reference["Acceleration"][k - 1])
    assert record.fs == 400.0 == float(reference["Fs"].item())
    assert record.x.dtype == record.y.dtype == np.float64


def test_f16_csv_reads_the_named_columns_and_fs_of_the_first_row(f16_dir):
    path = f16_dir / "F16Data_FullMSine_Level3.csv"
    assert hashlib.sha256(path.read_bytes()).hexdigest() == F16_SHA256[path.name], "not the published file"
    record = read_record(path, Layout("Force", "Acceleration2"))
    reference = np.genfromtxt(path, delimiter=",", skip_header=1, usecols=(0, 3, 5))
    assert len(record.x) == len(record.y) == 9 * 8192 == len(reference)
    np.testing.assert_array_equal(record.x, reference[:, 0])
    np.testing.assert_array_equal(record.y, reference[:, 1])
    assert record.fs == 400.0 == reference[0, 2]
    # One name works for both formats: the MAT's 3×N matrix and the CSV's own column.
    assert read_record(path, Layout("Voltage", "Acceleration3")).fs == 400.0


@pytest.mark.parametrize(
    ("file", "k", "samples"), [("WH_EstimationExample.csv", 3, 8192), ("WH_TestDataset.csv", 2, 16384)]
)
def test_wiener_hammerstein_groups_name_their_columns(wh_dir, file, k, samples):
    """``"r",,,…,"u",,,…`` : u names the columns after it up to the next name; u3 is the third."""
    path = wh_dir / file
    record = read_record(path, Layout(f"u{k}", f"y{k}"))
    reference = np.genfromtxt(path, delimiter=",", skip_header=1)
    width = (reference.shape[1] - 2) // 3  # r, u, y groups, fs, and the trailing comma's column
    assert len(record.x) == samples == len(reference)
    np.testing.assert_array_equal(record.x, reference[:, width + k - 1])
    np.testing.assert_array_equal(record.y, reference[:, 2 * width + k - 1])
    assert record.fs == 78125.0 == reference[0, 3 * width]


@pytest.mark.parametrize(("file", "count"), [("WH_EstimationExample.csv", 10), ("WH_TestDataset.csv", 2)])
def test_groups_named_for_both_x_and_y_are_records_pair_by_pair(wh_dir, file, count):
    """``u`` and ``y`` on a file of realisations side by side: one record a pair, (u_k, y_k), as
    each is read alone; one signal named of each is one record."""
    path = wh_dir / file
    records = read_record_set(path, Layout("u", "y"))
    pairs = [(f"u{k}", f"y{k}") for k in range(1, count + 1)]
    assert [(layout.x, layout.y) for layout, _ in records] == pairs
    for k, (_, record) in enumerate(records, start=1):
        alone = read_record(path, Layout(f"u{k}", f"y{k}"))
        np.testing.assert_array_equal(record.x, alone.x)
        np.testing.assert_array_equal(record.y, alone.y)
        assert record.fs == alone.fs == 78125.0
    ((layout, record),) = read_record_set(path, Layout("u2", "y2"))
    assert layout == Layout("u2", "y2")
    np.testing.assert_array_equal(record.y, read_record(path, Layout("u2", "y2")).y)


def test_matrices_named_for_both_x_and_y_are_records_row_by_row():
    forces, accelerations = np.arange(600.0).reshape(2, 300), -np.arange(600.0).reshape(2, 300)
    data = mat_file(matrix("Force", forces), matrix("Acc", accelerations), matrix("Fs", np.array([[400.0]])))
    records = parse_record_set(data, ".mat", Layout("Force", "Acc"))
    assert [(layout.x, layout.y) for layout, _ in records] == [("Force1", "Acc1"), ("Force2", "Acc2")]
    for k, (_, record) in enumerate(records):
        np.testing.assert_array_equal(record.x, forces[k])
        np.testing.assert_array_equal(record.y, accelerations[k])
        assert record.fs == 400.0


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b'"a",,"b",,,\n1,2,3,4,5\n', "'a' holds 2 signals and 'b' 3: as records, x and y must pair"),
        (b'"a",,"b"\n1,2,3\n', "'a' holds 2 signals: name one of them, a1 … a2; or, to read a record from"),
        (b'"a","b",\n1,2,3\n', "'b' holds 2 signals: name one of them, b1 … b2; or, to read a record from"),
    ],
)  # fmt: skip
def test_groups_that_do_not_pair_one_to_one_are_refused(content, message):
    with pytest.raises(InputError, match=re.escape(message)):
        parse_record_set(content, ".csv", Layout("a", "b"))


def test_silverbox_is_sugar_for_v1_v2_at_its_rate(silverbox_dir):
    data = (silverbox_dir / "SNLS80mV.csv").read_bytes()
    record = parse_silverbox(data)
    again = read_record(silverbox_dir / "SNLS80mV.csv", SILVERBOX)
    assert np.array_equal(record.x, again.x) and np.array_equal(record.y, again.y) and record.fs == again.fs
    reference = np.genfromtxt(io.BytesIO(data), delimiter=",", skip_header=1, usecols=(0, 1))
    np.testing.assert_array_equal(record.x, reference[:, 0])
    np.testing.assert_array_equal(record.y, reference[:, 1])
    assert record.fs == 1e7 / 2**14
    assert parse_csv(data, layout=Layout("V1", "V2")).fs is None  # the file itself states no rate


def test_mat_v4_and_compressed_v5_read_alike(tmp_path):
    force, acceleration = np.arange(50.0), np.arange(150.0).reshape(3, 50) ** 2
    variables = {"Force": force, "Acceleration": acceleration, "Fs": 400.0}
    for version, options in (("4", {}), ("5", {"do_compression": True}), ("5", {"do_compression": False})):
        path = tmp_path / f"v{version}{options}.mat"
        scipy.io.savemat(path, variables, format=version, **options)
        record = read_record(path, Layout("Force", "Acceleration2"))
        np.testing.assert_array_equal(record.x, force)
        np.testing.assert_array_equal(record.y, acceleration[1])
        assert record.fs == 400.0
    # A matrix stored with its samples down the columns, as MATLAB users often do: N×3.
    scipy.io.savemat(tmp_path / "tall.mat", {"u": force, "a": acceleration.T})
    np.testing.assert_array_equal(read_record(tmp_path / "tall.mat", Layout("u", "a3")).y, acceleration[2])


def test_a_record_split_over_two_files_reads_each_signal_from_its_own(tmp_path):
    # Bouc–Wen publishes each test signal as a 1×N variable in a file named as it.
    u, y = np.sin(np.arange(300.0)), np.cos(np.arange(300.0))
    scipy.io.savemat(tmp_path / "uval.mat", {"uval": u})
    scipy.io.savemat(tmp_path / "yval.mat", {"yval": y, "fs": 750.0})
    record = read_split_record(tmp_path / "uval.mat", tmp_path / "yval.mat", Layout("uval", "yval", 100.0))
    np.testing.assert_array_equal(record.x, u)
    np.testing.assert_array_equal(record.y, y)
    assert record.fs == 750.0  # the rate a file states wins over the layout's
    scipy.io.savemat(tmp_path / "short.mat", {"yval": y[:200]})
    with pytest.raises(InputError, match=r"uval\.mat holds 300 samples of 'uval' but .*short\.mat holds 200"):
        read_split_record(tmp_path / "uval.mat", tmp_path / "short.mat", Layout("uval", "yval"))
    scipy.io.savemat(tmp_path / "u400.mat", {"uval": u, "fs": 400.0})
    with pytest.raises(InputError, match=r"u400\.mat states a sampling rate of 400\.0 Hz but .* 750\.0 Hz"):
        read_split_record(tmp_path / "u400.mat", tmp_path / "yval.mat", Layout("uval", "yval"))
    with pytest.raises(InputError, match=r"yval\.mat: the MAT file has no variable 'y'"):
        read_split_record(tmp_path / "uval.mat", tmp_path / "yval.mat", Layout("uval", "y"))


def test_bouc_wen_test_signals_read_as_published():
    folder = benchmark_data("bouc-wen", "uval_multisine.mat", "yval_multisine.mat")
    record = read_split_record(
        folder / "uval_multisine.mat",
        folder / "yval_multisine.mat",
        Layout("uval_multisine", "yval_multisine"),
    )
    for signal, name in ((record.x, "uval_multisine"), (record.y, "yval_multisine")):
        np.testing.assert_array_equal(signal, scipy.io.loadmat(folder / f"{name}.mat")[name].ravel())
    assert record.x.size == 8192


def test_a_structs_fields_are_read_by_their_path_as_variables_are(tmp_path):
    """A field of a struct (``data.u``), of a struct within it, and the rows of a matrix field,
    from compressed and uncompressed files alike, as Simulink logs them ("Structure With Time")."""
    time = np.arange(200) / 400.0
    force, responses = np.sin(time * 60), np.vstack([np.cos(time * 60), time**2])
    variables = {
        "force": {"time": time, "signals": {"values": force[:, None], "label": "F"}},
        "yout": {"time": time, "signals": {"values": responses.T, "dimensions": 2.0}},
        "fs": 400.0,
    }
    for options in ({"do_compression": True}, {"do_compression": False}):
        path = tmp_path / f"simulink{options}.mat"
        scipy.io.savemat(path, variables, **options)
        record = read_record(path, Layout("force.signals.values", "yout.signals.values2"))
        np.testing.assert_array_equal(record.x, force)
        np.testing.assert_array_equal(record.y, responses[1])
        assert record.fs == 400.0
    independent = scipy.io.loadmat(path, simplify_cells=True)["yout"]["signals"]["values"][:, 0]
    np.testing.assert_array_equal(
        read_record(path, Layout("force.time", "yout.signals.values1")).y, independent
    )


@pytest.mark.parametrize(
    ("layout", "message"),
    [
        (
            Layout("data.u", "data.z"),
            r"no variable 'data\.z'; it holds data \(1×1 struct\), fs \(1×1 double\), "
            r"data\.u \(1×300 double\), data\.note \(1×2 char\), data\.inner\.y \(1×300 double\); "
            r"a struct's fields are named as data\.FIELD",
        ),
        (Layout("u", "y"), r"no variable 'u'; it holds data \(1×1 struct\), fs \(1×1 double\); a struct's"),
        (
            Layout("data", "data.u"),
            r"data \(1×1 struct\) is a struct: name one of its fields, as data\.FIELD",
        ),
        (Layout("data.u", "data.note"), r"data\.note \(1×2 char\) is not a real numeric array"),
        (Layout("data.u", "data.inner"), r"no variable 'data\.inner'; it holds .* data\.inner\.y "),
        (Layout("data.u", "fs.y"), r"no variable 'fs\.y'"),
    ],
)
def test_a_struct_field_that_is_not_a_signal_is_named_with_what_the_struct_holds(layout, message):
    values = np.arange(300.0)
    stream = io.BytesIO()
    scipy.io.savemat(stream, {"data": {"u": values, "note": "hi", "inner": {"y": values**2}}, "fs": 10.0})
    with pytest.raises(InputError, match=message):
        parse_mat(stream.getvalue(), LIMIT, layout)


def test_an_array_of_structs_is_refused_naming_its_dimensions():
    stream = io.BytesIO()
    both = np.array([(np.ones(5), np.ones(5))] * 2, dtype=[("u", object), ("y", object)])
    scipy.io.savemat(stream, {"runs": both})
    with pytest.raises(InputError, match=r"'runs' is an array of 1×2 structs; only a single struct's"):
        parse_mat(stream.getvalue(), LIMIT, Layout("runs.u", "runs.y"))


# --- errors that say what to fix ----------------------------------------------------------------


def test_mat_without_the_named_variables_lists_what_it_holds(f16_dir):
    message = (
        r"F16Data_SineSw_Level3\.mat: the MAT file has no variable 'Acc2'; it holds "
        r"Force \(1×108477 double\), Voltage \(1×108477 double\), "
        r"Acceleration \(3×108477 double\), Fs \(1×1 double\)"
    )
    with pytest.raises(InputError, match=message):
        read_record(f16_dir / "F16Data_SineSw_Level3.mat", Layout("Force", "Acc2"))
    # Without names, x and y are looked for, and the error says what there is instead.
    with pytest.raises(InputError, match="no variable 'x'; it holds Force"):
        read_record(f16_dir / "F16Data_SineSw_Level3.mat")


def test_a_column_that_does_not_exist_lists_the_columns(f16_dir, wh_dir):
    with pytest.raises(
        InputError,
        match="the CSV has no column 'Acceleration'; its columns are Force, Voltage, Acceleration1, "
        "Acceleration2, Acceleration3, Fs",
    ):
        read_record(f16_dir / "F16Data_FullMSine_Level3.csv", Layout("Force", "Acceleration"))
    with pytest.raises(
        InputError,
        match=r"no column 'v1'; its columns are r \(10 columns, r1 … r10\), u \(10 columns, u1 … u10\), "
        r"y \(10 columns, y1 … y10\), fs",
    ):
        read_record(wh_dir / "WH_EstimationExample.csv", Layout("v1", "y1"))


@pytest.mark.parametrize(
    ("file", "layout", "message"),
    [
        (WH_EST, Layout("u11", "y1"), "'u11' is out of range: 'u' holds 10 signal(s), u1 … u10"),
        (WH_EST, Layout("u0", "y1"), "'u0' is out of range"),
        (WH_EST, Layout("u", "y1"), "'u' holds 10 signals: name one of them, u1 … u10"),
        (F16_MAT, Layout("Force", "Acceleration4"), "'Acceleration' holds 3 signal(s)"),
        (F16_MAT, Layout("Force", "Acceleration"), "name one of them, Acceleration1"),
    ],
)  # fmt: skip
def test_a_group_index_out_of_range_is_named(f16_dir, wh_dir, file, layout, message):
    with pytest.raises(InputError, match=re.escape(message)):
        read_record((f16_dir if file == F16_MAT else wh_dir) / file, layout)


def test_names_match_in_another_case_when_no_other_does():
    record = parse_csv(b'"X","Y"\n1,2\n')  # as the x,y reader has always read it
    assert (record.x[0], record.y[0]) == (1.0, 2.0)
    assert parse_csv(b"U,u,Y\n1,2,3\n", layout=Layout("u", "y")).x[0] == 2.0  # its own case first
    with pytest.raises(InputError, match="no column 'ab'"):
        parse_csv(b"Ab,AB,y\n1,2,3\n", layout=Layout("ab", "y"))  # two in other cases: neither
    data = mat_file(matrix("Force", np.ones((1, 3))), matrix("ACC", np.ones((2, 3))))
    assert parse_mat(data, LIMIT, Layout("force", "acc2")).y.size == 3


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b'"a","b",\n1,2,\n3,,\n4,,\n', r"x \('a'\) has 3 samples but y \('b'\) has 1"),
        (b'"a","b",\n1,2,\n3,,\n4,5,\n', "CSV line 4: column 'b' has a value after its empty cell on line 3"),
        (b'"a","b",\n1,2,\n3,volts,\n', "CSV line 3: 'volts' in column 'b' is not a number"),
        (b'"a","b"\n1,2,7\n', "CSV line 2: expected 2 values, found 3"),
        (b'"a","b",\n1,2,7\n', "'b' holds 2 signals: name one of them, b1 … b2"),
        (b'"a",,"a"\n1,2,3\n', "names the column 'a' twice"),
        (b"# fs=100\na,b,fs\n1,2,200\n", "the '# fs=' comment says 100 Hz but the column 'fs' says 200 Hz"),
        (b"a,b,fs\n1,2,fast\n", "the sampling rate 'fast' is not a number"),
        (b",,\n1,2\n", "names no column"),
    ],
)
def test_malformed_named_csv_is_refused_with_the_line(content, message):
    with pytest.raises(InputError, match=message):
        parse_csv(content, layout=Layout("a", "b"))


def test_mat_signals_of_different_lengths_and_unusable_variables_are_named():
    x, y = np.ones((1, 300)), np.arange(200.0).reshape(1, 200)
    data = mat_file(
        matrix("x", x),
        matrix("y", y),
        matrix("square", np.eye(3)),
        matrix("cube", np.ones((2, 3, 300))),
        matrix("tall", np.arange(600.0).reshape(300, 2)),
        huge_cell("notes", 3),
        matrix("fs", np.array([[1.0, 2.0]])),
    )
    with pytest.raises(InputError, match="fs \\(1×2 double\\) must be one number"):
        parse_mat(data, LIMIT)
    data = data[: data.rfind(matrix("fs", np.array([[1.0, 2.0]])))]
    with pytest.raises(InputError, match=r"x \('x'\) has 300 samples but y \('y'\) has 200"):
        parse_mat(data, LIMIT)
    with pytest.raises(InputError, match=r"square \(3×3 double\) is not a vector, nor a matrix"):
        parse_mat(data, LIMIT, Layout("x", "square2"))
    with pytest.raises(InputError, match=r"notes \(1×3 cell\) is not a real numeric array"):
        parse_mat(data, LIMIT, Layout("x", "notes"))
    with pytest.raises(InputError, match=r"cube \(2×3×300 double\) is not a vector, nor a matrix"):
        parse_mat(data, LIMIT, Layout("x", "cube2"))
    np.testing.assert_array_equal(parse_mat(data, LIMIT, Layout("x", "tall2")).y, np.arange(1.0, 600.0, 2.0))


def test_mat_with_many_variables_is_refused_before_they_are_read():
    data = mat_file(*(matrix(f"v{index}", np.ones((1, 1))) for index in range(300)))
    with pytest.raises(InputError, match="holds more than 256 variables"):
        parse_mat(data, LIMIT)


def test_empty_variables_hold_no_values():
    data = mat_file(matrix("x", np.ones((0, 5))), matrix("y", np.ones((1, 5))))
    with pytest.raises(InputError, match=r"x \('x'\) holds no values"):
        parse_mat(data, LIMIT)


def test_mat_v73_is_refused_with_how_to_save_it():
    with pytest.raises(
        InputError, match=r"v7\.3 \(HDF5\) file, which is not read: save it with .*'-v7'.* or as CSV"
    ):
        parse_mat(v73_file(), LIMIT)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "too short"),
        (b"MATLAB 5.0" + bytes(200), "not a MAT file"),
        (mat_file(matrix("x", np.ones((1, 3))))[:-9], "cut off"),
        (mat_file(matrix("x", np.ones((1, 3))), matrix("x", np.ones((1, 3)))), "holds the variable"),
        (mat_file(compressed(matrix("x", np.ones((1, 3))))[:40]), "cut off"),
    ],
)
def test_malformed_mat_is_refused_with_the_reason(data, message):
    with pytest.raises(InputError, match=message):
        parse_mat(data, LIMIT)


# --- hostile MAT files: bounded memory, no pickle ------------------------------------------------


def test_mat_bomb_in_a_named_variable_is_refused_before_it_is_inflated():
    """400 MB of zeros in 400 kB: refused on its declared dimensions, within a megabyte."""
    bomb = mat_file(zeros_bomb("x", (1, 50_000_000), 400_000_000), matrix("y", np.ones((1, 300))))
    assert len(bomb) < 500_000
    with pytest.raises(
        RecordTooLargeError, match=r"the MAT variables x, y unpack to more than the upload limit"
    ):
        parse_mat(bomb, LIMIT)
    assert peak_allocation(lambda: parse_mat(bomb, LIMIT)) < 2**20


def test_mat_variable_whose_data_outgrows_its_dimensions_is_refused_before_inflating():
    """Dimensions 1×300 (within the limit), a data element declaring 400 MB behind them."""
    bomb = mat_file(zeros_bomb("x", (1, 300), 400_000_000), matrix("y", np.ones((1, 300))))
    with pytest.raises(
        InputError, match=r"MAT variable x \(1×300 double\) declares \d+ bytes, more than its values"
    ):
        parse_mat(bomb, LIMIT)
    assert peak_allocation(lambda: parse_mat(bomb, LIMIT)) < 2**20


def test_a_struct_whose_fields_inflate_beyond_a_bound_is_refused_as_it_is_walked():
    """A compressed struct of a few hundred kilobytes whose first field inflates to 400 MB of
    zeros before the fields named: refused once four times the upload limit is inflated, its
    memory within a megabyte; without a bound (a local file) the fields after it are read."""
    bomb = mat_file(struct_bomb("data", 400 * 2**20, {"u": np.arange(5.0)[None], "y": np.ones((1, 5))}))
    assert len(bomb) < 500_000
    with pytest.raises(InputError, match=r"the MAT struct 'data' unpacks to more than 67108864 bytes"):
        parse_mat(bomb, LIMIT, Layout("data.u", "data.y"))
    assert peak_allocation(lambda: parse_mat(bomb, LIMIT, Layout("data.u", "data.y"))) < 2**20
    fields = {"junk": np.zeros((1, 2**18)), "u": np.arange(5.0)[None], "y": np.ones((1, 5))}
    honest = mat_file(compressed(struct_element("data", fields)))
    np.testing.assert_array_equal(parse_mat(honest, None, Layout("data.u", "data.y")).x, np.arange(5.0))


def test_variables_not_named_are_never_inflated_nor_built():
    """A bomb and a cell array of 2³¹ − 1 cells (16 GB of object pointers to a reader that trusts
    its dimensions) beside x and y: the record reads, within a megabyte."""
    x, y = np.arange(300.0).reshape(1, 300), np.ones((1, 300))
    data = mat_file(
        matrix("x", x),
        zeros_bomb("junk", (1, 50_000_000), 400_000_000),
        huge_cell("cells", 2**31 - 1),
        matrix("y", y),
    )
    record = parse_mat(data, LIMIT)
    np.testing.assert_array_equal(record.x, x.ravel())
    assert peak_allocation(lambda: parse_mat(data, LIMIT)) < 2**20


def test_mat_samples_are_bounded_like_every_format():
    """A record holds at most limit/16 samples; a MAT file reads whole variables, all counted."""
    x = np.zeros((1, 1000))
    data = mat_file(compressed(matrix("x", x)), compressed(matrix("y", x)))
    assert parse_mat(data, 16_000).x.size == 1000
    with pytest.raises(RecordTooLargeError, match="unpack to more than the upload limit"):
        parse_mat(data, 15_999)


# --- the header parser, fuzzed ----------------------------------------------------------------

NAMES = st.text(alphabet="abcdefghijklmnopqrstuvwxyzABCXYZ_ .-", min_size=1, max_size=12).filter(
    lambda name: name.strip() == name and name.lower() != "fs"
)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(NAMES, st.integers(1, 4), st.booleans()), min_size=1, max_size=6, unique_by=lambda g: g[0]
    ),
    st.booleans(),
    st.integers(0, 2),
)
def test_every_column_of_a_grouped_header_is_found_by_its_name(groups, trailing_comma, unnamed):
    """Any header of names (quoted or not), each followed by empty cells for the rest of its
    group, after ``unnamed`` empty cells, with or without trailing commas; two rows whose cell in
    column c holds c and 100 + c. NAME (or NAMEk) reads the column it names."""
    header = [""] * unnamed
    for name, width, quoted in groups:
        header += [f'"{name}"' if quoted else name] + [""] * (width - 1)
    end = "," if trailing_comma else ""
    columns = range(len(header))
    text = ",".join(header) + end + "\n"
    text += "".join(",".join(str(row * 100 + c) for c in columns) + end + "\n" for row in (0, 1))
    column = unnamed
    for name, width, _ in groups:
        for k in {1, width}:
            signal = name if width == 1 else f"{name}{k}"
            record = parse_csv(text, layout=Layout(signal, signal))
            np.testing.assert_array_equal(record.x, [column + k - 1, 100 + column + k - 1])
        column += width
    _, count = header_groups(",".join(header) + end)
    assert count == len(header) + trailing_comma


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), st.sampled_from(["u2", "y1", "fs", "r", "zz"]))
def test_named_csv_parser_never_crashes(tail, name):
    data = b'"r",,"u",,"y",,"fs",\n1,2,3,4,5,6,78125,\n' + tail
    try:
        record = parse_csv(data, layout=Layout(name, "y2"))
    except InputError:
        return
    assert record.x.dtype == record.y.dtype == np.float64 and record.x.shape == record.y.shape


VALID_MAT = mat_file(
    matrix("Force", np.ones((1, 20))),
    compressed(matrix("Acc", np.ones((3, 20)))),
    matrix("Fs", np.array([[400.0]])),
)


_v4 = io.BytesIO()
scipy.io.savemat(_v4, {"Force": np.ones(20), "Acc": np.ones((3, 20)), "Fs": 400.0}, format="4")
VALID_V4 = _v4.getvalue()


def test_a_variable_whose_values_have_an_unknown_data_type_is_refused_not_a_crash():
    """Found by the fuzz test below in a whole-suite run: seven bytes replaced over the end of
    Fs's name and its values' tag, which then holds an unknown data type code (51435 where
    miDOUBLE, 9, was). scipy's reader indexed its type table with it and the process died (SIGBUS
    or SIGSEGV, from run to run). Parsed in a child process, so that a crash fails this test
    instead of ending the run."""
    damaged = VALID_MAT[:464] + bytes.fromhex("2465db7a47ebc8") + VALID_MAT[471:]
    child = (
        "import sys\n"
        "from models.errors import InputError\n"
        "from recordfiles.reader import Layout, parse_mat\n"
        "try:\n"
        f"    parse_mat(sys.stdin.buffer.read(), {LIMIT}, Layout('Force', 'Acc2'))\n"
        "except InputError as error:\n"
        "    print(error)\n"
    )
    run = subprocess.run([sys.executable, "-c", child], input=damaged, capture_output=True, timeout=120)
    assert run.returncode == 0, f"the parser died ({run.returncode}): {run.stderr.decode()[-400:]}"
    assert "Fs (1×1 double stored as data type 51435) is not a real numeric array" in run.stdout.decode(), (
        run.stdout
    )


def _struct_file(compress: bool) -> bytes:
    stream = io.BytesIO()
    fields = {"u": np.ones(20), "inner": {"y": np.ones((2, 20)), "note": "hi"}, "e": np.zeros((0, 0))}
    scipy.io.savemat(stream, {"data": fields, "fs": 400.0}, do_compression=compress)
    return stream.getvalue()


VALID_STRUCTS = [_struct_file(compress=True), _struct_file(compress=False)]


# Each valid file with the names read from it: flat variables (v5, v4) and a struct's fields.
VALID_FILES = [
    (VALID_MAT, Layout("Force", "Acc2")),
    (VALID_V4, Layout("Force", "Acc2")),
    *((valid, Layout("data.u", "data.inner.y2")) for valid in VALID_STRUCTS),
]


@settings(max_examples=800, deadline=None)
@given(
    st.sampled_from(VALID_FILES),
    st.floats(0, 1),
    st.integers(0, 16),
    st.binary(min_size=1, max_size=16),
)
def test_mat_parser_never_crashes_on_a_damaged_file(valid, where, cut, patch):
    (content, layout) = valid
    at = int(where * (len(content) - 1))
    data = content[:at] + patch + content[at + cut :]
    try:
        record = parse_mat(data, LIMIT, layout)
    except InputError:
        return
    assert record.x.dtype == record.y.dtype == np.float64 and record.x.shape == record.y.shape
