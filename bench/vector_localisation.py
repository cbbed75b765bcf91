"""Localisation with one sensor against five, on the 5-mass chain: the figures issue 16 asks for.

    .venv/bin/python -m bench.vector_localisation [--records 250] [--noise 1e-6]

The chain of simulator.chain with its defaults (five 10 kg masses, 50 kN/m springs k1 … k5 from
the wall, 300 N·s/m dampers; 1500 Hz), the force of 25 kN std on mass 1, an unmeasured 800 N force
disturbance on it, and ``--noise`` [m] of white noise on every displacement sensor. One vector
fault-mode model per spring (:mod:`models.vector`), trained on five 2000-sample experiments at
k = −8, −4, 0, 4, 8 %: with all five displacements, lags 2 (the scheme's exact order); with the
displacement of mass 1 alone (or of mass 5), an ARX model of order 10 (a 5-mass chain seen from
one coordinate). Then ``--records`` faulty records, the springs in turn, k drawn uniformly over
3 … 8 %, are inspected with each set of models; a record is localised correctly when a fault is
detected and put on its spring. It also prints how often the 95 % interval k̂ ± 1.96·σ̂_k of the
right mode covers k. Seeds are fixed: a rerun prints the same figures.
"""

from __future__ import annotations

import argparse

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import numpy as np
from scipy import stats

from bench.false_alarms import Progress, interval
from models.vector import VectorFNARX, fit_vector_fnarx, inspect_vector
from simulator.chain import ChainParameters, ChainScenario, simulate_chain
from simulator.options import DAMPING, MASS, STIFFNESS

SAMPLES = 2000
DISTURBANCE = 800.0  # N, on mass 1
TRAINING_K = (-8.0, -4.0, 0.0, 4.0, 8.0)
CHAIN = ChainParameters.build(5, [MASS], [STIFFNESS], [DAMPING])
SPRINGS = CHAIN.springs[:5]  # k6, to the far wall, is absent


def record(fault: str, k: float, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """x [N] and the five displacements [m] as an (N, 5) array."""
    scenario = ChainScenario(CHAIN, fault, k, disturbance_std=DISTURBANCE, y_noise_std=noise)
    simulated = simulate_chain(scenario, SAMPLES, seed)
    return simulated.x, np.column_stack([simulated.responses[f"y{m}"] for m in range(1, 6)])


def models(noise: float, channels: slice, lags: int) -> list[VectorFNARX]:
    """One model per spring from the training experiments' ``channels``."""
    fitted = []
    for index, spring in enumerate(SPRINGS):
        experiments = []
        for j, k in enumerate(TRAINING_K):
            x, y = record(spring, k, noise, seed=1000 + 10 * index + j)
            experiments.append((x, y[:, channels], k))
        fitted.append(fit_vector_fnarx(spring, experiments, lags=lags))
    return fitted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--records", type=int, default=250, help="faulty records, the springs in turn")
    parser.add_argument(
        "--noise", type=float, default=1e-6, help="sensor noise std [m] on every displacement"
    )
    arguments = parser.parse_args()
    sensors = {
        "all five (lags 2)": (slice(0, 5), 2),
        "mass 1 alone (order 10)": (slice(0, 1), 10),
        "mass 5 alone (order 10)": (slice(4, 5), 10),
    }
    trained = {name: models(arguments.noise, channels, lags) for name, (channels, lags) in sensors.items()}
    rng = np.random.default_rng(7)
    right = dict.fromkeys(sensors, 0)
    covered = dict.fromkeys(sensors, 0)
    z = stats.norm.ppf(0.975)
    progress = Progress("faulty records", arguments.records, 50)
    for i in range(arguments.records):
        spring = SPRINGS[i % len(SPRINGS)]
        k = float(rng.uniform(3.0, 8.0))
        x, y = record(spring, k, arguments.noise, seed=5000 + i)
        for name, (channels, _) in sensors.items():
            verdict = inspect_vector(x, y[:, channels], trained[name])
            right[name] += verdict.localised == spring
            mode = next(m for m in verdict.modes if m.name == spring)
            covered[name] += abs(mode.k_hat - k) <= z * mode.sigma_k
        progress.step()
    n = arguments.records
    print(
        f"Localisation of {n} faulty records (k uniform over 3 … 8 %, springs k1 … k5 in turn; "
        f"{DISTURBANCE:g} N disturbance on mass 1, sensor noise {arguments.noise:g} m)"
    )
    for name in sensors:
        print(
            f"   {name:24s} localised correctly {interval(right[name], n)}; "
            f"the 95 % interval covers k in {covered[name]}/{n}"
        )


if __name__ == "__main__":
    main()
