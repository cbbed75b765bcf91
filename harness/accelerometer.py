"""A structure that is not the rig: three masses watched by a driving-point accelerometer, with
sensor noise on both measured signals; the tests of baseline-only monitoring and
bench/novelty_rates.py watch it."""

from __future__ import annotations

import dataclasses
import functools
import uuid

import httpx
import numpy as np

from harness.api_helpers import API, create_structure, npz_bytes, post_record, stored
from simulator.chain import ChainParameters, ChainScenario, simulate_chain

# Three masses, a driving-point accelerometer at 1 kHz: heavily damped, as the explicit scheme needs.
CHAIN = ChainParameters.build(3, [10.0, 20.0, 15.0], [50e3, 80e3, 30e3], [2000.0], ts=1e-3)
FORCE = 1000.0  # N
NOISE = 0.01  # of each healthy signal's RMS, on x and on y
ALPHA = 0.05  # the designed false-alarm rate the tests judge at (the service's default NARXWATCH_ALPHA)


@functools.cache
def _trained() -> ChainScenario:
    """The chain at the training force with its sensors' noise. Made once a process: the noise
    floor is measured on a simulated healthy record that costs several of the records the tests
    draw, and every scenario below shares it."""
    trained = ChainScenario(CHAIN, excitation_std=FORCE, outputs=(1,), response="acceleration")
    return trained.with_sensor_noise(NOISE)


def scenario(fault: str = "none", k: float = 0.0, level: float = 1.0) -> ChainScenario:
    """The chain at ``level`` times the training force, its sensors' noise a floor: 1 % of the
    healthy signals' RMS at the training level, whatever the level."""
    return dataclasses.replace(_trained(), fault=fault, k=k, excitation_std=level * FORCE)


def record(s: ChainScenario, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    simulated = simulate_chain(s, n, seed)
    return simulated.x, simulated.responses["y1"]


# The structure of the chain's baseline through the API (tests/test_api_novelty.py, the
# dashboard's browser tests) and in tests/test_novelty.py: an ARX(8, 8) with no delay, the
# accelerometer feeling the force at once. Given, not chosen: choosing a baseline's terms is
# tested on its own (tests/test_novelty.py, tests/test_api_baseline_choice.py).
TERMS = [f"y[t-{i}]" for i in range(1, 9)] + ["x[t]"] + [f"x[t-{i}]" for i in range(1, 8)]
FS = 1000.0  # the chain's sampling rate
# Four short healthy records, and a few records judged: through the API what is tested is that
# each record gets the judgement ``models.novelty`` makes of it; the rates that judgement holds
# are tests/test_novelty.py's, on its own records. The service fits the baseline and its
# jackknife, one output-error refit a record, and the tests fit them again to compare: more
# records would cost both fits in proportion to their square and test nothing more (an 8 % loss
# of k2 over 4000 samples still stands far out of the noise of a baseline from four).
TRAINING, TRAINING_SAMPLES, SAMPLES = 4, 2000, 4000
HEALTHY, FAULTY = 10, 5


def upload(client, structure_id: int, x: np.ndarray, y: np.ndarray, **params) -> dict:
    return stored(
        post_record(client, structure_id, npz_bytes(x=x, y=y, fs=FS), "application/x-npz", **params)
    )


def healthy_training() -> list[tuple[np.ndarray, np.ndarray]]:
    return [record(scenario(), TRAINING_SAMPLES, 100 + i) for i in range(TRAINING)]


def chain_baseline(
    admin: httpx.Client, ingest: httpx.Client, training: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[int, dict]:
    """A new chain structure with the ``training`` records and a baseline trained from them: its
    id and the baseline's version."""
    structure_id = create_structure(admin, f"chain-{uuid.uuid4().hex[:8]}", fs=FS)["id"]
    ids = [upload(ingest, structure_id, x, y)["id"] for x, y in training]
    response = admin.post(
        f"{API}/structures/{structure_id}/models/baseline", json={"record_ids": ids, "terms": TERMS}
    )
    assert response.status_code == 201, response.text
    return structure_id, response.json()
