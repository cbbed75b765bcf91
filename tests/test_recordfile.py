"""Record files: exact round trips and a clear refusal of every malformed input."""

from __future__ import annotations

import hashlib
import io

import numpy as np
import pytest
from conftest import SILVERBOX_SHA256

from models.errors import InputError
from service.recordfiles import RecordTooLargeError, parse_csv, parse_npz, parse_silverbox, read_record
from simulator.recordfile import dump_csv, dump_npz, write_record


@pytest.fixture
def signals() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    return rng.normal(0, 25e3, 50), rng.normal(0, 0.08, 50) * np.pi


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip_is_exact(tmp_path, signals, suffix):
    x, y = signals
    path = write_record(tmp_path / f"r{suffix}", x, y, 1500.0)
    record = read_record(path)
    np.testing.assert_array_equal(record.x, x)
    np.testing.assert_array_equal(record.y, y)
    assert record.fs == 1500.0


def test_csv_layout_is_comment_header_rows(signals):
    text = dump_csv(*signals, 1500.0)
    lines = text.splitlines()
    assert lines[0] == "# fs=1500"
    assert lines[1] == "x,y"
    assert len(lines) == 2 + len(signals[0])


def test_csv_without_fs_comment_and_with_quoted_header():
    record = parse_csv(b'"x","y"\n1,2\n3,4\n\n')
    assert record.fs is None
    np.testing.assert_array_equal(record.x, [1.0, 3.0])
    np.testing.assert_array_equal(record.y, [2.0, 4.0])


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "no header"),
        (b"# fs=1500\n", "no header"),
        (b"a,b\n1,2\n", "header must be 'x,y'"),
        (b"x,y\n", "no data rows"),
        (b"x,y\n1,2\n3,4,5\n", "line 3: expected 2 values"),
        (b"x,y\n1,2\nfoo,4\n", "line 3"),
        (b"# fs=abc\nx,y\n1,2\n", "not a number"),
        (b"# fs=-5\nx,y\n1,2\n", "positive"),
        (b"\xff\xfe\x00x", "not UTF-8"),
    ],
)
def test_malformed_csv_is_refused_with_the_reason(content, message):
    with pytest.raises(InputError, match=message):
        parse_csv(content)


def test_csv_nan_parses_so_validation_can_name_the_sample():
    record = parse_csv(b"x,y\n1,2\nnan,4\n")
    assert np.isnan(record.x[1])


def test_npz_with_pickled_objects_is_refused():
    buffer = io.BytesIO()
    np.savez(buffer, x=np.array([{"a": 1}], dtype=object), y=np.zeros(1))
    with pytest.raises(InputError, match="never unpickled"):
        parse_npz(buffer.getvalue())


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"x": np.zeros(3)}, "lacks array"),
        ({"x": np.array(["a", "b"]), "y": np.zeros(2)}, "must be numeric"),
        ({"x": np.zeros(2), "y": np.zeros(2), "fs": np.array("fast")}, "not a number"),
    ],
)
def test_malformed_npz_is_refused(arrays, message):
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    with pytest.raises(InputError, match=message):
        parse_npz(buffer.getvalue())


def test_not_a_zip_is_refused():
    with pytest.raises(InputError, match="not a readable NPZ"):
        parse_npz(b"PK but not really a zip archive")


def test_unknown_suffix_and_missing_file_are_named(tmp_path):
    with pytest.raises(InputError, match="unknown record format"):
        read_record(tmp_path / "r.txt")
    with pytest.raises(InputError, match="cannot read the file"):
        read_record(tmp_path / "missing.csv")


def test_npz_carries_fs_as_scalar(signals):
    record = parse_npz(dump_npz(*signals, 610.35))
    assert record.fs == pytest.approx(610.35)


def test_bare_npy_is_not_taken_for_an_npz():
    buffer = io.BytesIO()
    np.save(buffer, np.zeros(4))
    with pytest.raises(InputError, match="not a readable NPZ"):
        parse_npz(buffer.getvalue())


def test_npz_member_that_is_not_an_array_is_refused():
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("x.txt", "1,2,3")
        archive.writestr("y.npy", b"not an array")
    with pytest.raises(InputError):
        parse_npz(buffer.getvalue())


def test_npz_that_unpacks_beyond_the_limit_is_refused_before_loading():
    pattern = np.tile([0.0, 1.0], 500_000)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, x=pattern, y=pattern)
    assert len(buffer.getvalue()) < 100_000
    with pytest.raises(RecordTooLargeError, match="upload limit"):
        parse_npz(buffer.getvalue(), max_bytes=1_000_000)
    assert parse_npz(buffer.getvalue(), max_bytes=16_000_000).x.size == 1_000_000


@pytest.mark.parametrize("name", sorted(SILVERBOX_SHA256))
def test_silverbox_files_read_as_published(silverbox_dir, name):
    data = (silverbox_dir / name).read_bytes()
    assert hashlib.sha256(data).hexdigest() == SILVERBOX_SHA256[name], "not the published file"
    record = parse_silverbox(data)
    assert record.fs == 1e7 / 2**14
    assert len(record.x) == len(record.y) == 131_072
    # The first and last data rows, read independently of the parser.
    rows = [line.split(",") for line in data.decode().splitlines() if line.strip()]
    header = [cell.strip('"') for cell in rows[0]]
    v1, v2 = header.index("V1"), header.index("V2")
    assert (record.x[0], record.y[0]) == (float(rows[1][v1]), float(rows[1][v2]))
    assert (record.x[-1], record.y[-1]) == (float(rows[-1][v1]), float(rows[-1][v2]))
    assert np.all(np.isfinite(record.x)) and np.all(np.isfinite(record.y))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('"x","y",\n1,2,\n', "columns 'V1' and 'V2'"),
        ('"V1","V2",\n1,2,\n3,volts,\n', "not numbers"),
        ('"V1","V2",\n', "no data rows"),
        (b"\xff\xfe", "not UTF-8"),
    ],
)
def test_malformed_silverbox_file_is_refused_with_the_reason(content, message):
    with pytest.raises(InputError, match=message):
        parse_silverbox(content)
