"""Record files: exact round trips and a clear refusal of every malformed input."""

from __future__ import annotations

import hashlib
import io
import re
import tracemalloc
import zipfile
import zlib
from collections.abc import Callable

import numpy as np
import pytest

from harness.api_helpers import npz_bytes
from harness.npz_bombs import bomb_member, bomb_npz, cut_off_header_npz, npy, npy_header, stored, zip_archive
from harness.prerequisites import SILVERBOX_SHA256
from models.errors import InputError
from recordfiles.conditions import MAX_CONDITIONS, Condition
from recordfiles.reader import (
    MAX_CSV_COLUMNS,
    MAX_CSV_LINE,
    Layout,
    RecordTooLargeError,
    parse_csv,
    parse_npz,
    parse_record_set,
    parse_silverbox,
    read_record,
    record_samples,
)
from recordfiles.writer import dump_csv, dump_npz, write_record


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
        (b"a,b\n1,2\n", "no column 'x'; its columns are a, b"),
        (b"x,y\n", "no data rows"),
        (b"x,y\n1,2\n3,4,5\n", "line 3: expected 2 values"),
        (b"x,y\n1,2\nfoo,4\n", "line 3"),
        (b"# fs=abc\nx,y\n1,2\n", "not a number"),
        (b"# fs=-5\nx,y\n1,2\n", "positive"),
        (b"\xff\xfe\x00x", "not UTF-8"),
        # Spreadsheets set to a decimal comma export ';' between values; tab-separated text too.
        (b"x;y\n0,5;1,25\n", "values are separated by ';', where a CSV's are by ','"),
        (b"x\ty\n0.5\t1.25\n", "values are separated by '\\\\t', where a CSV's are by ','"),
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
        ('"x","y",\n1,2,\n', "no column 'V1'; its columns are x, y"),
        ('"V1","V2",\n1,2,\n3,volts,\n', "CSV line 3: 'volts' in column 'V2' is not a number"),
        ('"V1","V2",\n', "no data rows"),
        (b"\xff\xfe", "not UTF-8"),
    ],
)
def test_malformed_silverbox_file_is_refused_with_the_reason(content, message):
    with pytest.raises(InputError, match=message):
        parse_silverbox(content)


# --- hostile archives: refused before anything is decompressed ---------------------------------

LIMIT = 16 * 2**20  # the service's default upload limit


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


@pytest.mark.parametrize(
    ("member", "error", "message"),
    [
        ("fs", InputError, "NPZ member 'fs' must be one number"),
        ("temperature", InputError, "NPZ member 'temperature' must be one number"),
        ("x", RecordTooLargeError, "unpack to more than the upload limit"),
        ("y", RecordTooLargeError, "unpack to more than the upload limit"),
    ],
)
def test_npz_bomb_in_any_member_is_refused_with_bounded_memory(member, error, message):
    x, y = np.ones(300), np.arange(300.0)
    bomb = bomb_npz(x, y, bomb=member, items=50_000_000)  # 400 MB of zeros in 400 kB
    assert len(bomb) < 500_000
    with pytest.raises(error, match=message):
        parse_npz(bomb, LIMIT)
    assert peak_allocation(lambda: parse_npz(bomb, LIMIT)) < 2**20


def test_npz_member_whose_zip_sizes_lie_is_refused_by_its_npy_header():
    """The zip's declared size can be small while the .npy header declares gigabytes: both count."""
    compressed, _, _ = bomb_member(50_000_000)
    header = npy_header("<f8", (50_000_000,))
    first = zlib.crc32(header + bytes(4096 - len(header)))  # the CRC of what the zip says it holds
    archive = zip_archive({"x.npy": (compressed, 8, 4096, first), "y.npy": stored(npy(np.ones(3)))})
    with pytest.raises(RecordTooLargeError, match="'x': 400000000 bytes"):
        parse_npz(archive, LIMIT)
    assert peak_allocation(lambda: parse_npz(archive, LIMIT)) < 2**20


def test_npz_fs_holding_more_than_one_number_is_refused():
    message = r"NPZ member 'fs' must be one number, but its header declares shape \(10,\) of float64"
    with pytest.raises(InputError, match=message):
        parse_npz(npz_bytes(x=np.ones(3), y=np.ones(3), fs=np.full(10, 1500.0)), LIMIT)
    with pytest.raises(InputError, match=r"the sampling rate array\(\[1500., 1500.\]\) is not a number"):
        parse_npz(npz_bytes(x=np.ones(3), y=np.ones(3), fs=np.full(2, 1500.0)), LIMIT)


def test_npz_with_a_cut_off_npy_header_is_refused_with_the_reason():
    with pytest.raises(InputError, match=r"NPZ member 'y' has a malformed \.npy header"):
        parse_npz(cut_off_header_npz(np.ones(3)), LIMIT)


def test_npz_members_beside_x_y_fs_are_scalar_conditions_and_nothing_else():
    archive = npz_bytes(x=np.ones(3), y=np.ones(3), fs=1500.0, notes=np.zeros(3))
    with pytest.raises(
        InputError, match=r"NPZ member 'notes' holds 3 values \(shape \(3,\)\); a condition is one"
    ):
        parse_npz(archive, LIMIT)
    channels = npz_bytes(x=np.ones(300), y=np.ones(300), y2=np.ones(300))  # a second channel
    message = (
        "NPZ member 'y2' must be one number, but its header declares shape (300,) of float64; every "
        "member beside x, y and fs is an operating condition"
    )
    with pytest.raises(InputError, match=re.escape(message)):
        parse_npz(channels, LIMIT)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in ("x.npy", "y.npy"):
            archive.writestr(name, npy(np.ones(3)))
        archive.writestr("notes.txt", b"recorded on the north span")
    with pytest.raises(
        InputError, match=r"may hold only \.npy arrays \(x, y, fs and one number per condition\); it"
    ):
        parse_npz(buffer.getvalue(), LIMIT)


@pytest.mark.parametrize(("suffix", "unit"), [(".csv", "°C"), (".npz", None)])
def test_the_simulators_conditions_read_back_exactly(tmp_path, signals, suffix, unit):
    """The simulator writes a record's temperature as ``# temperature=… °C`` or as a scalar member
    (which has no unit): read back to the last digit."""
    path = write_record(
        tmp_path / f"r{suffix}", *signals, 1500.0, {"temperature": 12.345678901234567, "level": -3}
    )
    assert read_record(path).conditions == (
        Condition("level", -3.0),
        Condition("temperature", 12.345678901234567, unit),
    )


def test_the_unitless_comment_of_earlier_simulator_files_is_read():
    record = parse_csv("# fs=1500\n# temperature=12.5\nx,y\n1,2\n")
    assert record.conditions == (Condition("temperature", 12.5),)


def test_csv_conditions_are_assignment_comments_before_the_header():
    text = (
        "# a record of the north span, 12 = 3 * 4\n"  # prose: its first word is not followed by "="
        "#temperature = -4.5  °C  \n"
        "# fs=1500\n"
        "\n"
        "# excitation_level=2e-1 N\n"
        "x,y\n1,2\n3,4\n"
    )
    record = parse_csv(text)
    assert record.fs == 1500.0
    assert record.conditions == (
        Condition("excitation_level", 0.2, "N"),
        Condition("temperature", -4.5, "°C"),
    )
    assert parse_csv("x,y\n1,2\n").conditions == ()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("# temperature=12.5 deg C\n", "the unit 'deg C' of condition 'temperature' is not allowed"),
        (
            "# temperature=\n",
            "CSV line 1: the condition 'temperature' has the value '', which is not a number",
        ),
        ("# t=1\n# u=2\n# t=3\n", "the condition 't' is given twice"),
        ("# y=1\n", "'y' cannot name a condition"),
        ("# Fs=1500 Hz\n", "CSV line 1: the '# fs=' comment holds the sampling rate in Hz"),
        ("".join(f"# v{i}=0\n" for i in range(17)), "a record may carry at most 16 conditions"),
    ],
)
def test_malformed_csv_conditions_are_refused_with_the_reason(text, message):
    with pytest.raises(InputError, match=re.escape(message)):
        parse_csv(text + "x,y\n1,2\n")


def test_csv_with_endless_condition_lines_is_refused_at_the_first_too_many():
    text = b"# t=1\n" * 1_000_000 + b"x,y\n1,2\n"
    with pytest.raises(InputError, match="a record may carry at most 16 conditions"):
        parse_csv(text)
    assert peak_allocation(lambda: parse_csv(text)) < 80 * 2**20  # the text's lines, not a million conditions


def test_npz_with_more_members_than_a_record_has_is_refused_before_any_is_read():
    conditions = {f"v{index}": np.float64(index) for index in range(MAX_CONDITIONS)}
    assert (
        len(parse_npz(npz_bytes(x=np.ones(3), y=np.ones(3), fs=1500.0, **conditions), LIMIT).conditions) == 16
    )
    archive = npz_bytes(x=np.ones(3), y=np.ones(3), fs=1500.0, extra=np.float64(1), **conditions)
    with pytest.raises(
        InputError, match="the NPZ holds 20 members; a record holds the arrays x, y and fs and"
    ):
        parse_npz(archive, LIMIT)


def test_npz_with_a_long_member_list_is_refused_before_zipfile_reads_it():
    """Ten thousand empty members: zipfile would build ten thousand entries before any name is checked."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name in ("x.npy", "y.npy"):
            archive.writestr(name, npy(np.ones(3)))
        for index in range(10_000):
            archive.writestr(f"m{index}", b"")
    data = buffer.getvalue()
    with pytest.raises(InputError, match=r"the NPZ lists 10002 members in a \d+-byte directory"):
        parse_npz(data, LIMIT)
    assert peak_allocation(lambda: parse_npz(data, LIMIT)) < 2**20


def test_npz_with_the_same_member_twice_is_refused():
    x = stored(npy(np.ones(3)))
    archive = zip_archive({"x.npy": x, "y.npy": x}).replace(b"y.npy", b"x.npy")
    with pytest.raises(InputError, match="the same array twice"):
        parse_npz(archive, LIMIT)


def test_csv_keeps_every_digit_of_the_rate(tmp_path):
    path = write_record(tmp_path / "r.csv", np.arange(3.0), np.arange(3.0) ** 2, 1500.0000001)
    assert read_record(path).fs == 1500.0000001


@pytest.mark.parametrize("method", [8, 12, 14, 99], ids=["deflate", "bzip2", "lzma", "unknown"])
def test_npz_member_whose_compressed_data_is_corrupt_is_refused(method):
    good = npy(np.ones(3))
    corrupt = (b"\xff" * 50, method, len(good), zlib.crc32(good))
    archive = zip_archive({"x.npy": corrupt, "y.npy": stored(good)})
    with pytest.raises(InputError, match="NPZ"):
        parse_npz(archive, LIMIT)


def test_csv_with_more_rows_than_a_record_may_hold_is_refused_before_parsing():
    """Rows of "0,1" pack a sample in 4 bytes: a body within the limit would otherwise unpack to
    several times its size in Python objects."""
    rows = b"x,y\n" + b"0,1\n" * 1000
    assert parse_csv(rows, max_samples=1000).x.size == 1000
    message = "the CSV has more than 1000 samples; a record may hold at most 1000 samples"
    with pytest.raises(RecordTooLargeError, match=message):
        parse_csv(rows + b"0,1\n", max_samples=1000)
    assert record_samples(16 * 2**20) == 2**20  # x and y as float64, as an NPZ within the limit holds them


# --- CSV shapes whose cells would cost many times the text: refused on its separators ----------

WIDE = 8 * 2**20  # bytes of each hostile body, as an upload of half the default limit
AT_MOST = "; a record file may have at most 512"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (b"x,y" + b",c" * (WIDE // 2) + b"\n1,2\n", "CSV line 1 has 4194306 columns" + AT_MOST),
        (b"x,y" + b"," * WIDE + b"\n1,2\n", "CSV line 1 has 8388610 columns" + AT_MOST),
        (b"x,y" + b",c" * 600 + b"\n1,2\n", "the CSV header has 602 columns" + AT_MOST),
        (b"x,y\n" + b"1," * (WIDE // 2) + b"2\n", "CSV line 2 has 4194305 columns" + AT_MOST),
        (b"x,y\n1,2" + b"0" * WIDE + b"\n", "CSV line 2 has 8388611 characters; a line of a record file may"),
        (b"x,y\n1,2," + b" 3," * 600 + b"\n", "CSV line 2: expected 2 values, found 603"),
        (b"x,y\n" + b"1,2\r" * (WIDE // 4), "the CSV has more than 1048576 samples"),
    ],
    ids=["wide-header", "empty-columns", "600-columns", "wide-row", "long-line", "wide-trailing", "cr-lines"],
)
def test_a_csv_wider_or_longer_than_a_record_is_refused_in_a_few_times_its_size(body, message):
    """A header of a million columns cost thirty times its size (a dict entry and a list per
    cell) and seconds before it was refused; a row alike, and lines ended by "\\r" (which the
    count of "\\n" before splitting missed) one string each. Each is refused with the bound it
    passed, having cost at most the decoded text, the block it lies in and the line."""
    with pytest.raises(InputError, match=re.escape(message)):
        parse_csv(body, record_samples(LIMIT))
    assert peak_allocation(lambda: parse_csv(body, record_samples(LIMIT))) < 3.5 * len(body) + 2**16


def test_the_widest_csv_a_record_set_needs_is_read():
    """As many pairs as a refinement fits, each beside its reference (Wiener–Hammerstein's r, u,
    y groups), fs and the trailing comma MATLAB writes: within the column bound."""
    pairs = 100
    header = ",".join(f'"{name}"' + "," * (pairs - 1) for name in "ruy") + ',"fs",'
    rows = "".join(",".join(str(row + c) for c in range(3 * pairs)) + ",1500,\n" for row in range(3))
    assert header.count(",") < MAX_CSV_COLUMNS and len(rows.splitlines()[0]) < MAX_CSV_LINE
    records = parse_record_set((header + "\n" + rows).encode(), ".csv", Layout("u", "y"), LIMIT)
    assert len(records) == pairs
    (last, record) = records[-1]
    assert (last.x, last.y, record.fs) == ("u100", "y100", 1500.0)
    np.testing.assert_array_equal(record.y, [299, 300, 301])


def test_short_rows_cost_at_most_their_numbers_beside_the_text():
    """Rows of "0,1" are 4 bytes a sample and 16 bytes as float64: the lines are split a block at
    a time, never all held as strings (which cost 60 bytes a line more)."""
    body = b"x,y\n" + b"0,1\n" * 2**18
    record = parse_csv(body, record_samples(LIMIT))
    assert record.x.size == 2**18
    assert peak_allocation(lambda: parse_csv(body, record_samples(LIMIT))) < 8 * len(body)


def test_a_column_of_times_gives_the_rate_only_where_asked_and_none_is_stated():
    """On the command line's layout a CSV that states no rate takes it from its column of times;
    a stated rate stands (its times unread); the service's layout reads no times, and a column
    named t that is read as a signal is a signal."""
    times = Layout(times=True)
    timed = "Time,x,y\n" + "".join(f"{k / 400:.6g},{k},{-k}\n" for k in range(1000))
    assert parse_csv(timed, layout=times).fs == pytest.approx(400.0, rel=1e-9)
    assert parse_csv(timed).fs is None
    assert parse_csv("# fs=500\n" + "t,x,y\n0,1,2\n0,3,4\n", layout=times).fs == 500.0
    as_signal = parse_csv("x,t\n1,0\n2,5\n", layout=Layout(y="t", times=True))
    assert as_signal.fs is None and list(as_signal.y) == [0.0, 5.0]
    with pytest.raises(InputError, match="the column 't' holds 1 time"):
        parse_csv("t,x,y\n0,1,2\n", layout=times)
