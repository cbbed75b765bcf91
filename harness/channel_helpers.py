"""A structure watched by several sensors: records of the simulator's 3-mass chain (every mass's
displacement, channels a1, a2, a3, 1 µm of sensor noise) and vector fault modes k2 and k3 trained
over HTTP from three records each; short records (1000 samples) so that it takes seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.api_helpers import API, Org, clients, create_structure, post_record, stored
from harness.live import LiveServer
from simulator.chain import ChainParameters, ChainScenario, simulate_chain
from simulator.options import DAMPING, MASS, STIFFNESS

N = 1000
CHAIN = ChainParameters.build(3, [MASS], [STIFFNESS], [DAMPING])
FS = float(round(1 / CHAIN.ts))  # as simulator.chain states its records
NAMES = ("a1", "a2", "a3")
TRAINING_K = (-8.0, 0.0, 8.0)
MODES = ("k2", "k3")


def chain_record(fault: str, k: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    scenario = ChainScenario(CHAIN, fault, k, disturbance_std=800.0, y_noise_std=1e-6)
    simulated = simulate_chain(scenario, N, seed)
    return simulated.x, np.column_stack([simulated.responses[f"y{m}"] for m in (1, 2, 3)])


def channels_body(x: np.ndarray, y: np.ndarray, names: tuple[str, ...] = NAMES, **extra: object) -> dict:
    channels = [{"name": name, "y": y[:, j].tolist()} for j, name in enumerate(names)]
    return {"x": x.tolist(), "channels": channels, "fs": FS, **extra}


def csv_text(x: np.ndarray, y: np.ndarray, names: tuple[str, ...] = NAMES) -> str:
    rows = "".join(",".join(f"{v:.17g}" for v in (a, *b)) + "\n" for a, b in zip(x, y, strict=True))
    return f"# fs={FS:.17g}\n" + ",".join(("x", *names)) + "\n" + rows


@dataclass
class Site:
    org: Org
    structure_id: int
    models: dict[str, dict]  # the vector modes' versions, as the trainings answered


def build_site(server: LiveServer, names: tuple[str, ...] = NAMES) -> Site:
    """A structure with vector modes k2 and k3 trained over HTTP from three records each, their
    channels called ``names``."""
    org = Org.create(server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, fs=FS)["id"]
        models = {}
        for m, mode in enumerate(MODES):
            experiments = [
                {
                    "record_id": stored(
                        post_record(
                            ingest, structure_id, channels_body(*chain_record(mode, k, 10 * m + i), names)
                        )
                    )["id"],
                    "k": k,
                }
                for i, k in enumerate(TRAINING_K)
            ]
            response = admin.post(
                f"{API}/structures/{structure_id}/models/vector-fault-modes",
                json={"name": mode, "experiments": experiments},
            )
            assert response.status_code == 201, response.text
            models[mode] = response.json()
    return Site(org, structure_id, models)
