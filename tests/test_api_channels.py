"""Records of several sensors and vector fault-mode models in the service (issue 16): uploads of
named channels in every format, vector trainings over HTTP, inspections of multi-channel records,
and the refusals, each leaving nothing behind (``api_helpers.nothing_written``).

Against the real app on a real SQLite file, with one round trip on PostgreSQL. The records come
from the simulator's 3-mass chain (every mass's displacement, 1 µm of sensor noise), short enough
for the file to run in seconds: 1000 samples, models of lags 2 from three experiments each.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    json_body,
    nothing_written,
    npz_bytes,
    post_record,
    stored,
    wait_for,
)
from harness.channel_helpers import (
    FS,
    MODES,
    NAMES,
    TRAINING_K,
    N,
    Site,
    build_site,
    chain_record,
    channels_body,
    csv_text,
)
from harness.cli import invoke
from harness.dashboard_helpers import DASHBOARD, charts, logged_in
from harness.live import LiveServer
from models.vector import fit_vector_fnarx, inspect_vector
from service.domain.schedules import RUN_SCHEDULE


@pytest.fixture(scope="module")
def site(sqlite_api_server: LiveServer) -> Site:
    return build_site(sqlite_api_server)


def test_a_record_of_several_channels_is_judged_by_the_vector_models(site: Site):
    """A 6 % k2 fault is found in k2, with the figures the library computes from the same models;
    every mode carries Hosking's test and each channel's residual RMS by name."""
    assert site.models["k2"]["training"]["channels"] == list(NAMES)
    x, y = chain_record("k2", 6.0, 500)
    with site.org.client("ingest") as ingest:
        uploaded = stored(post_record(ingest, site.structure_id, channels_body(x, y), inspect="true"))
    assert uploaded["channels"] == list(NAMES)
    verdict = uploaded["verdict"]
    assert verdict["status"] == "faulty" and verdict["fault_mode"] == "k2", verdict
    assert verdict["q_critical_detection"] is None and verdict["z_critical"] > 2
    low, high = verdict["interval"]
    assert low < 6.0 < high
    # The library's own inspection with models fitted from the same records gives the same k̂.
    local = [
        fit_vector_fnarx(mode, [(*chain_record(mode, k, 10 * m + i), k) for i, k in enumerate(TRAINING_K)])
        for m, mode in enumerate(MODES)
    ]
    expected = inspect_vector(x, y, local)
    for mode, figures in zip(verdict["modes"], expected.modes, strict=True):
        assert mode["name"] == figures.name
        assert mode["k_hat"] == pytest.approx(figures.k_hat, rel=1e-6)
        assert mode["q"] == pytest.approx(figures.whiteness.q, rel=1e-6)
        assert mode["residual_variance"] == pytest.approx(figures.generalised_variance, rel=1e-6)
        assert list(mode["channel_rms"]) == list(NAMES)
        assert list(mode["channel_rms"].values()) == pytest.approx(figures.channel_rms, rel=1e-6)
    with site.org.client("viewer") as viewer:
        assert viewer.get(f"{API}/verdicts/{verdict['id']}").json() == verdict


def test_the_record_page_draws_each_channels_residual(site: Site, sqlite_api_server: LiveServer):
    """The dashboard's page of a vector verdict draws the chosen mode's residual on every channel:
    the very residual whose RMS the verdict recorded."""
    x, y = chain_record("k3", 6.0, 504)
    with site.org.client("ingest") as ingest:
        verdict = stored(post_record(ingest, site.structure_id, channels_body(x, y), inspect="true"))[
            "verdict"
        ]
    with logged_in(sqlite_api_server, site.org.keys["viewer"]) as viewer:
        page = viewer.get(f"{DASHBOARD}/records/{verdict['record_id']}")
    assert page.status_code == 200, page.text
    drawn = charts(page)
    assert sorted(drawn) == [f"residual-{name}" for name in NAMES]
    mode = next(m for m in verdict["modes"] if m["name"] == verdict["reference_mode"])
    for name in NAMES:
        residual = np.asarray(drawn[f"residual-{name}"]["data"][0]["y"])
        assert len(residual) == N - 2
        assert np.sqrt(np.mean(residual**2)) == pytest.approx(mode["channel_rms"][name], rel=1e-9)
    assert "Hosking" in page.text


def test_channels_are_matched_by_name_in_any_order(site: Site):
    """The same record with its channels uploaded in another order is another record, judged alike."""
    x, y = chain_record("k3", 5.0, 501)
    with site.org.client("ingest") as ingest:
        first = stored(post_record(ingest, site.structure_id, channels_body(x, y), inspect="true"))["verdict"]
        order = [2, 0, 1]
        shuffled = channels_body(x, y[:, order], tuple(NAMES[j] for j in order))
        second = stored(post_record(ingest, site.structure_id, shuffled, inspect="true"))["verdict"]
    assert second["record_id"] != first["record_id"]
    assert second["fault_mode"] == first["fault_mode"] == "k3"
    assert [m["k_hat"] for m in second["modes"]] == pytest.approx(
        [m["k_hat"] for m in first["modes"]], rel=1e-9
    )


def test_csv_npz_and_mat_name_the_same_channels_as_json(site: Site):
    """The same data as JSON, CSV (named columns, ?y= repeated), NPZ (members) and MAT (variables)
    are one record: each later upload answers 200 with the first's id."""
    x, y = chain_record("none", 0.0, 502)
    params = {"y": list(NAMES)}
    with site.org.client("ingest") as ingest:
        first = stored(post_record(ingest, site.structure_id, channels_body(x, y)))
        assert first["created"] and first["channels"] == list(NAMES)
        arrays = {name: y[:, j] for j, name in enumerate(NAMES)}
        mat = io.BytesIO()
        scipy.io.savemat(mat, {"x": x, "fs": FS, **arrays})
        bodies = [
            (csv_text(x, y), "text/csv"),
            (npz_bytes(x=x, fs=FS, **arrays), "application/x-npz"),
            (mat.getvalue(), "application/x-matlab-data"),
        ]
        for content, media in bodies:
            again = ingest.post(
                f"{API}/structures/{site.structure_id}/records",
                content=content,
                headers={"Content-Type": media},
                params=params,
            )
            assert again.status_code == 200, (media, again.text)
            assert again.json()["id"] == first["id"] and again.json()["channels"] == list(NAMES)


def test_a_record_of_one_response_is_stored_as_before(site: Site):
    """Its answer says no channels, and its hash is that of fs, x and y as always."""
    body = json_body(300, fs=FS)
    with site.org.client("ingest") as ingest:
        record = stored(post_record(ingest, site.structure_id, body))
    assert "channels" not in record
    digest = hashlib.sha256(np.float64(FS).tobytes())
    digest.update(np.asarray(body["x"], dtype="<f8").tobytes() + np.asarray(body["y"], dtype="<f8").tobytes())
    assert record["sha256"] == digest.hexdigest()


def test_a_queued_inspection_of_several_channels_gives_the_same_verdict(site: Site):
    x, y = chain_record("k2", 4.0, 503)
    with site.org.client("ingest") as ingest:
        response = post_record(ingest, site.structure_id, channels_body(x, y), inspect="queue")
        assert response.status_code == 202, response.text
        record_id = response.json()["id"]
        verdicts = wait_for(
            lambda: [
                v
                for v in ingest.get(f"{API}/structures/{site.structure_id}/verdicts").json()["items"]
                if v["record_id"] == record_id
            ],
            30,
            "the queued vector inspection",
        )
        inspected = stored(ingest.post(f"{API}/records/{record_id}/inspect"))
    assert verdicts[0] == inspected and inspected["fault_mode"] == "k2"  # type: ignore[index]


def test_a_schedule_inspects_records_of_several_channels_with_the_vector_models(site: Site):
    """A structure whose only models are vector ones: its schedule's run inspects the records
    stored uninspected, with those models, and succeeds. (It used to fail at every due time,
    looking for models for a record of one response.)"""
    with clients(site.org) as (admin, ingest, viewer):
        pending = [
            stored(
                post_record(
                    ingest,
                    site.structure_id,
                    channels_body(*chain_record("k2", 4.0, 600 + i)),
                    inspect="false",
                )
            )["id"]
            for i in range(2)
        ]
        body = {"action": "inspect_pending", "interval_seconds": 3600}
        created = admin.post(f"{API}/structures/{site.structure_id}/schedules", json=body)
        assert created.status_code == 201, created.text

        def ran() -> list[str]:
            return [
                job["state"]
                for job in admin.get(f"{API}/jobs").json()["items"]
                if job["task"] == RUN_SCHEDULE
            ]

        wait_for(lambda: ran() and ran()[0] in ("done", "failed"), 60, "the schedule's run")
        assert ran() == ["done"], admin.get(f"{API}/jobs").json()["items"]
        judged = {
            v["record_id"]: v
            for v in viewer.get(f"{API}/structures/{site.structure_id}/verdicts").json()["items"]
        }
        assert set(pending) <= judged.keys()
        assert {judged[record_id]["fault_mode"] for record_id in pending} == {"k2"}
        assert (
            admin.delete(f"{API}/structures/{site.structure_id}/schedules/{created.json()['id']}").status_code
            == 204
        )


# --- refused, nothing stored ---------------------------------------------------------------


def refused(site: Site, body: dict | str | bytes, expected: int, *words: str, **params: object) -> None:
    media = "text/csv" if isinstance(body, str) else None
    with nothing_written(site.org, site.structure_id), site.org.client("ingest") as ingest:
        response = post_record(ingest, site.structure_id, body, media, **params)
        assert response.status_code == expected, response.text
        for word in words:
            assert word in detail(response), detail(response)


def test_channels_named_otherwise_than_the_models_are_refused_naming_them(site: Site):
    x, y = chain_record("k2", 5.0, 510)
    refused(
        site, channels_body(x, y, ("a1", "a2", "b3")), 422, "lacks a3", "also has b3", "'k2'", inspect="true"
    )
    refused(site, channels_body(x, y[:, :2], ("a1", "a2")), 422, "lacks a3", inspect="queue")


def test_channels_of_different_lengths_are_refused(site: Site):
    x, y = chain_record("none", 0.0, 511)
    body = channels_body(x, y)
    body["channels"][1]["y"] = body["channels"][1]["y"][:-5]
    refused(site, body, 422, "'a2' has 995")
    text = csv_text(x, y).splitlines()
    text[-3:] = [line.rsplit(",", 1)[0] + "," for line in text[-3:]]  # a3 ends three rows early
    refused(site, "\n".join(text) + "\n", 422, "'a3'", "997", y=list(NAMES))


def test_a_channel_named_twice_is_refused(site: Site):
    x, y = chain_record("none", 0.0, 512)
    refused(site, channels_body(x, y, ("a1", "a2", "a1")), 422, "'a1' is given twice")
    refused(site, csv_text(x, y), 422, "'a1' is given twice", y=["a1", "a2", "a1"])


def test_too_many_channels_are_refused(site: Site):
    x, y = chain_record("none", 0.0, 513)
    wide = np.column_stack([y] * 3)
    names = tuple(f"c{j}" for j in range(9))
    refused(site, channels_body(x, wide, names), 422, "at most 8")
    refused(site, csv_text(x, wide, names), 422, "at most 8", y=list(names))
    refused(site, channels_body(x, y[:, :1], ("a1",)), 422, "channels")


def test_a_record_of_several_channels_without_vector_models_is_a_conflict(sqlite_api_server: LiveServer):
    org = Org.create(sqlite_api_server)
    with clients(org) as (admin, _, _):
        structure_id = create_structure(admin, fs=FS)["id"]
    with nothing_written(org, structure_id), org.client("ingest") as ingest:
        response = post_record(
            ingest, structure_id, channels_body(*chain_record("none", 0.0, 514)), inspect="true"
        )
        assert response.status_code == 409 and "vector-fault-modes" in detail(response), response.text


def test_trainings_refuse_records_of_other_channels(site: Site):
    """A vector training over records whose channel sets differ, or of one response; a training of
    one response over a record of several: each a 422 naming the record, no version stored."""
    x, y = chain_record("k2", 0.0, 520)
    with site.org.client("ingest") as ingest:
        three = stored(post_record(ingest, site.structure_id, channels_body(x, y)))["id"]
        other = stored(
            post_record(ingest, site.structure_id, channels_body(x, y * 1.01, ("a1", "a2", "b3")))
        )["id"]
        two = stored(post_record(ingest, site.structure_id, channels_body(x, y[:, :2] * 1.02, ("a1", "a2"))))[
            "id"
        ]
        one = stored(post_record(ingest, site.structure_id, json_body(N, fs=FS)))["id"]
    url = f"{API}/structures/{site.structure_id}"
    cases = [
        (
            "models/vector-fault-modes",
            {"name": "k2", "experiments": [{"record_id": three, "k": 0}, {"record_id": other, "k": 8}]},
            f"record {other} has a1, a2, b3",
        ),
        (
            "models/vector-fault-modes",
            {"name": "k2", "experiments": [{"record_id": three, "k": 0}, {"record_id": two, "k": 8}]},
            f"record {two} has a1, a2",
        ),
        (
            "models/vector-fault-modes",
            {"name": "k2", "experiments": [{"record_id": three, "k": 0}, {"record_id": one, "k": 8}]},
            f"record {one} has one response",
        ),
        ("models/baseline", {"record_ids": [one, three]}, f"record {three} has 3 response channels"),
        (
            "refinements",
            {"record_ids": [three], "test_record_ids": [one], "base_model_id": site.models["k2"]["id"]},
            f"record {three} has 3 response channels",
        ),
    ]
    with nothing_written(site.org, site.structure_id), site.org.client("admin") as admin:
        for route, body, words in cases:
            response = admin.post(f"{url}/{route}", json=body)
            assert response.status_code == 422 and words in detail(response), response.text


@pytest.fixture(scope="module")
def chain_site(sqlite_api_server: LiveServer) -> Site:
    """A structure whose vector modes name the channels as the simulator does."""
    return build_site(sqlite_api_server, ("y1", "y2", "y3"))


@pytest.mark.parametrize("body", ["json", "npz"])
def test_the_simulator_posts_every_mass_of_a_chain(
    chain_site: Site, sqlite_api_server: LiveServer, body: str
):
    """``narxwatch-sim record --masses 3`` posts its three displacements as channels y1, y2, y3 and
    prints the verdict the structure's vector modes gave (its entry point in this process: the
    script as a process is ``test_sim_client``'s)."""
    site = chain_site
    args = ["record", "--masses", "3", "--fault", "k2", "--k", "6", "--seed", "5", "--format", body, "--json"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("NARXWATCH_SIM_")}
    env |= {"NARXWATCH_SIM_API_KEY": site.org.keys["ingest"], "NARXWATCH_SIM_URL": sqlite_api_server.url}
    where = ["--structure", str(site.structure_id)]
    result = invoke(*args, *where, cwd=Path.cwd(), check=False, script="narxwatch-sim", environ=env)
    assert result.returncode == 0, result.stderr
    verdict = json.loads(result.stdout)
    assert verdict["fault_mode"] == "k2" and list(verdict["modes"][0]["channel_rms"]) == ["y1", "y2", "y3"]
    with site.org.client("viewer") as viewer:
        assert viewer.get(f"{API}/verdicts/{verdict['id']}").json() == verdict


def test_postgresql_round_trip(postgresql_api_server: LiveServer):
    """Stored, trained and inspected on PostgreSQL: the verdict is the SQLite one's."""
    site = build_site(postgresql_api_server)
    x, y = chain_record("k2", 6.0, 500)
    with site.org.client("ingest") as ingest:
        verdict = stored(post_record(ingest, site.structure_id, channels_body(x, y), inspect="true"))[
            "verdict"
        ]
        record = ingest.post(f"{API}/records/{verdict['record_id']}/inspect").json()
    assert record == verdict
    assert verdict["fault_mode"] == "k2" and list(verdict["modes"][0]["channel_rms"]) == list(NAMES)
