"""Uploading the files as published (issue 14, deliverable 6): MAT bodies
(``application/x-matlab-data``) and CSVs with named columns, x and y named by the query parameters
``x`` and ``y``. Through HTTP against the real app on SQLite; a record set stored in one
transaction, found again when sent again, and refused whole on PostgreSQL too (``database_site``).
A refused upload leaves nothing behind (``api_helpers.nothing_written``).
"""

from __future__ import annotations

import io
import resource
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
import scipy.io

from harness.api_helpers import (
    API,
    FS,
    Org,
    clients,
    create_structure,
    detail,
    json_body,
    nothing_written,
    npz_bytes,
    post_record,
    raw_json,
)
from harness.live import DATABASES, LiveServer, on_each_database
from harness.mat_bombs import mat_file, matrix, v73_file, zeros_bomb
from harness.prerequisites import benchmark_file
from service.schemas import MAX_REFINEMENT_RECORDS

MAT = "application/x-matlab-data"


@dataclass
class Site:
    server: LiveServer
    org: Org
    rig: int  # fs = FS, no models: where the refused uploads are tried


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def build_site(api_server: LiveServer) -> Site:
    org = Org.create(api_server)
    with clients(org) as (admin, _, _):
        rig = create_structure(admin, "published")["id"]
    return Site(api_server, org, rig)


@pytest.fixture(scope="module")
def site(api_server: LiveServer) -> Site:
    return build_site(api_server)


@pytest.fixture(scope="module", params=DATABASES)
def database_site(request: pytest.FixtureRequest) -> Site:
    """The site on each database, for the record sets a transaction stores or refuses whole."""
    return on_each_database(request, "site", build_site)


@pytest.fixture(scope="module")
def f16_mat() -> Path:
    return benchmark_file("f16-gvt", "F16Data_SineSw_Level3.mat")


@pytest.fixture(scope="module")
def wh_csv() -> Path:
    return benchmark_file("wiener-hammerstein", "WH_EstimationExample.csv")


@pytest.fixture
def ingest(site: Site):
    with site.org.client("ingest") as client:
        yield client


def test_f16_mat_and_wh_csv_upload_as_the_records_they_hold(site: Site, ingest, f16_mat: Path, wh_csv: Path):
    """The stored record is the one an independent read gives: the same data uploaded again as an
    NPZ of it is recognised as already stored (same id, same sha256)."""
    with clients(site.org) as (admin, _, _):
        f16 = create_structure(admin, "f16", fs=400.0)["id"]
        wh = create_structure(admin, "wh", fs=78125.0)["id"]
    response = post_record(ingest, f16, f16_mat.read_bytes(), MAT, x="Force", y="Acceleration2")
    assert response.status_code == 201, response.text
    stored = response.json()
    assert stored["n_samples"] == 108_477 and stored["fs"] == 400.0
    reference = scipy.io.loadmat(f16_mat)
    again = post_record(
        ingest,
        f16,
        npz_bytes(x=reference["Force"].ravel(), y=reference["Acceleration"][1], fs=400.0),
        "application/x-npz",
    )
    assert again.status_code == 200 and (again.json()["id"], again.json()["sha256"]) == (
        stored["id"],
        stored["sha256"],
    )

    response = post_record(ingest, wh, wh_csv.read_bytes(), "text/csv", x="u3", y="y3")
    assert response.status_code == 201, response.text
    stored = response.json()
    assert stored["n_samples"] == 8192 and stored["fs"] == 78125.0
    columns = np.genfromtxt(wh_csv, delimiter=",", skip_header=1)
    again = post_record(
        ingest, wh, npz_bytes(x=columns[:, 12], y=columns[:, 22], fs=78125.0), "application/x-npz"
    )
    assert again.status_code == 200 and again.json()["id"] == stored["id"]


def _mat(**variables: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    scipy.io.savemat(buffer, variables)
    return buffer.getvalue()


rng = np.random.default_rng(8)
FORCE, ACC = rng.normal(size=300), rng.normal(0, 1e-3, (3, 300))
GROUPED = '"Force","Acc",,,"fs",\n' + "".join(
    f"{f:.17g},{a:.17g},{b:.17g},{c:.17g},{FS if i == 0 else ''},\n"
    for i, (f, a, b, c) in enumerate(zip(FORCE, *ACC, strict=True))
)


NOT_A_NUMBER = GROUPED.replace(f"{ACC[1, 7]:.17g}", "n/a")  # row 8 of the data, line 9 of the file
# id: (body, media type, query parameters, what the answer says)
BAD_UPLOADS = {
    "mat-variable": (
        _mat(Force=FORCE, Acceleration=ACC, Fs=FS),
        MAT,
        {"x": "Force", "y": "Acc2"},
        "the MAT file has no variable 'Acc2'; it holds Force (1×300 double), "
        "Acceleration (3×300 double), Fs (1×1 double)",
    ),
    "csv-column": (
        GROUPED,
        "text/csv",
        {"x": "Force", "y": "Acceleration2"},
        "the CSV has no column 'Acceleration2'; its columns are Force, Acc (3 columns, Acc1 … Acc3), fs",
    ),
    "group-index": (
        GROUPED,
        "text/csv",
        {"x": "Force", "y": "Acc4"},
        "'Acc4' is out of range: 'Acc' holds 3",
    ),
    "whole-matrix": (
        _mat(Force=FORCE, Acc=ACC),
        MAT,
        {"x": "Force", "y": "Acc"},
        "name one of them, Acc1 … Acc3",
    ),
    "lengths": (
        _mat(Force=FORCE[:299], Acc=ACC),
        MAT,
        {"x": "Force", "y": "Acc1"},
        "x ('Force') has 299 samples but y ('Acc1') has 300",
    ),
    "not-a-number": (
        NOT_A_NUMBER,
        "text/csv",
        {"x": "Force", "y": "Acc2"},
        "CSV line 9: 'n/a' in column 'Acc2' is not a number",
    ),
    "v7.3": (v73_file(), MAT, {}, "v7.3 (HDF5) file, which is not read: save it with"),
    "default-names": (
        mat_file(matrix("x", np.ones((1, 300)))),
        MAT,
        {},
        "no variable 'y'; it holds x (1×300 double)",
    ),
    "npz": (npz_bytes(x=FORCE, y=ACC[0], fs=FS), "application/x-npz", {"y": "Acc1"}, "an NPZ record holds"),
    "json": (
        raw_json(json_body(300)),
        "application/json",
        {"x": "Force"},
        "a JSON record has the fields x and y",
    ),
}


@pytest.mark.parametrize(
    ("body", "media", "names", "message"), list(BAD_UPLOADS.values()), ids=list(BAD_UPLOADS)
)
def test_bad_names_and_files_are_a_422_naming_what_to_fix(site: Site, ingest, body, media, names, message):
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, body, media, **names)
        assert response.status_code == 422, response.text
        assert message in detail(response), detail(response)


def test_named_upload_is_stored(site: Site, ingest):
    response = post_record(ingest, site.rig, GROUPED, "text/csv", x="Force", y="Acc2")
    assert response.status_code == 201, response.text
    assert response.json()["n_samples"] == 300 and response.json()["fs"] == FS


def test_a_simulink_log_uploads_by_its_fields_paths(site: Site, ingest):
    """x and y named as a struct's fields (MATLAB's "Structure With Time"): the record stored is
    the NPZ of the same signals (same id); a field the struct lacks is a 422 listing its fields."""
    force = {"time": np.arange(300) / FS, "signals": {"values": FORCE[:, None]}}
    response_log = {"time": np.arange(300) / FS, "signals": {"values": ACC.T}}
    body = _mat(force=force, response=response_log, fs=FS)  # type: ignore[arg-type]
    response = post_record(
        ingest, site.rig, body, MAT, x="force.signals.values", y="response.signals.values3"
    )
    assert response.status_code == 201, response.text
    again = post_record(ingest, site.rig, npz_bytes(x=FORCE, y=ACC[2], fs=FS), "application/x-npz")
    assert again.status_code == 200 and again.json()["id"] == response.json()["id"]
    with nothing_written(site.org, site.rig):
        missing = post_record(ingest, site.rig, body, MAT, x="force.signals.values", y="response.values")
        assert missing.status_code == 422, missing.text
        assert "no variable 'response.values'" in detail(missing)
        assert "response.signals.values (300×3 double)" in detail(missing)


def test_mat_bomb_is_refused_before_it_is_inflated(site: Site, ingest):
    """A 4 MB MAT file whose variable declares 4·10⁹ bytes of zeros: 413, and the server's peak
    memory does not grow by anything like it."""
    bomb = mat_file(zeros_bomb("x", (1, 500_000_000), 4_000_000_000), matrix("y", np.ones((1, 300))))
    assert 3_000_000 < len(bomb) < site.server.settings.max_upload_bytes
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    with nothing_written(site.org, site.rig):
        response = post_record(ingest, site.rig, bomb, MAT)
        assert response.status_code == 413, response.text
        assert "the MAT variables x, y unpack to more than the upload limit" in detail(response)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - before < 200 * 2**20


def post_set(client: httpx.Client, structure_id: int, body: bytes | str, media: str, **names: str):
    return client.post(
        f"{API}/structures/{structure_id}/record-sets",
        content=body,
        headers={"Content-Type": media},
        params=names,
    )


def test_a_file_of_realisations_uploads_as_its_records_in_one_request(database_site: Site, wh_csv: Path):
    """Wiener–Hammerstein's estimation file with x = u, y = y: its ten records (u1, y1) …
    (u10, y10), in that order, each the record an independent read gives (uploaded alone as an
    NPZ it is recognised as stored); the file again: 200, the same records, none created."""
    site = database_site
    with clients(site.org) as (admin, ingest, _):
        wh = create_structure(admin, "wh-set", fs=78125.0)["id"]
        response = post_set(ingest, wh, wh_csv.read_bytes(), "text/csv", x="u", y="y")
        assert response.status_code == 201, response.text
        stored = response.json()
        assert len(stored) == 10 and all(r["created"] and r["n_samples"] == 8192 for r in stored)
        assert len({r["id"] for r in stored}) == 10
        columns = np.genfromtxt(wh_csv, delimiter=",", skip_header=1)  # r1…r10, u1…u10, y1…y10, fs
        for k in (1, 4, 10):
            alone = npz_bytes(x=columns[:, 9 + k], y=columns[:, 19 + k], fs=78125.0)
            again = post_record(ingest, wh, alone, "application/x-npz")
            assert again.status_code == 200 and again.json()["id"] == stored[k - 1]["id"], again.text
        repeated = post_set(ingest, wh, wh_csv.read_bytes(), "text/csv", x="u", y="y")
        assert repeated.status_code == 200, repeated.text
        assert [r["id"] for r in repeated.json()] == [r["id"] for r in stored]
        assert not any(r["created"] for r in repeated.json())


def test_mat_matrices_upload_as_the_records_of_their_rows(site: Site, ingest):
    force, acc = rng.normal(size=(2, 300)), rng.normal(0, 1e-3, (2, 300))
    response = post_set(ingest, site.rig, _mat(F=force, A=acc, fs=FS), MAT, x="F", y="A")
    assert response.status_code == 201, response.text
    for k, record in enumerate(response.json()):
        again = post_record(ingest, site.rig, npz_bytes(x=force[k], y=acc[k], fs=FS), "application/x-npz")
        assert again.status_code == 200 and again.json()["id"] == record["id"]


PAIRS = '"F",,"A",\n' + "".join(
    f"{f:.17g},{g:.17g},{a:.17g},{b:.17g}\n" for f, g, a, b in zip(FORCE, FORCE[::-1], *ACC[:2], strict=True)
)
# The second record's response beyond what cubic terms over 300 samples may hold: refused when it
# is stored, after the first record was (in the same transaction).
TOO_LARGE = PAIRS.replace(f"{ACC[1, 7]:.17g}\n", f"{1e40:.17g}\n")
BAD_SETS = {
    "group-and-one": (PAIRS, "text/csv", {"x": "F", "y": "A2"}, 422, "to read a record from each pair"),
    "second-record": (TOO_LARGE, "text/csv", {"x": "F", "y": "A"}, 422, "the record (F2, A2) of the set:"),
    "json": (raw_json(json_body(300)), "application/json", {}, 415, "a record set is a CSV"),
    "npz": (npz_bytes(x=FORCE, y=ACC[0], fs=FS), "application/x-npz", {}, 415, "a record set is a CSV"),
}


@pytest.mark.parametrize(
    ("body", "media", "names", "status", "message"), list(BAD_SETS.values()), ids=list(BAD_SETS)
)
def test_a_refused_record_set_stores_none_of_its_records(
    database_site: Site, body, media, names, status, message
):
    site = database_site
    with site.org.client("ingest") as ingest:
        with nothing_written(site.org, site.rig):
            response = post_set(ingest, site.rig, body, media, **names)
            assert response.status_code == status, response.text
            assert message in detail(response), detail(response)
        if names == {"x": "F", "y": "A"}:
            assert "no record of the set was stored" in detail(response)
            mended = post_set(ingest, site.rig, PAIRS, "text/csv", **names)
            assert mended.status_code == 201, mended.text


def test_a_record_set_is_bounded_as_each_of_its_records_is(site: Site, ingest):
    """Short numbers in a set: "0,0,0,0" rows hold two records of limit/16 + 1 samples each
    within half the body limit; every record of a set holds at most limit/16 samples."""
    most = site.server.settings.max_upload_bytes // 16
    body = b'"F",,"A",\n' + b"0,1,0,1\n" * (most + 1)
    assert len(body) < site.server.settings.max_upload_bytes
    with nothing_written(site.org, site.rig):
        response = post_set(ingest, site.rig, body, "text/csv", x="F", y="A")
        assert response.status_code == 413, response.text
        assert f"a record may hold at most {most} samples" in detail(response)


def test_a_record_set_holds_at_most_as_many_records_as_a_refinement_fits(site: Site, ingest):
    """Each record of a set is checked and inserted under the write lock: 101 pairs of short
    columns (a few kB) would cost 101 ingests in one request. A set holds at most the 100 records a
    refinement fits (``MAX_REFINEMENT_RECORDS``); one more is a 422 naming the bound, nothing stored."""
    pairs = MAX_REFINEMENT_RECORDS + 1
    columns = rng.normal(size=(300, 2 * pairs))
    body = ",".join(['"F"'] + [""] * (pairs - 1) + ['"A"'] + [""] * (pairs - 1)) + "\n"
    body += "".join(",".join(f"{v:.6g}" for v in row) + "\n" for row in columns)
    with nothing_written(site.org, site.rig):
        response = post_set(ingest, site.rig, body, "text/csv", x="F", y="A")
        assert response.status_code == 422, response.text
        assert f"holds {pairs} records; a set may hold at most {MAX_REFINEMENT_RECORDS}," in detail(response)
