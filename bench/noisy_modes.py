"""Fault modes under sensor noise (models/free_run_inspection.py) against the paper's chain
(models/inspection.py), on the noisy 3-DOF accelerometer of harness/accelerometer.py: per fault
and magnitude, how often each localises the fault, how often its interval covers the truth, its
mean σ̂_k; and the healthy records' false alarms. First, what the record itself allows: the σ_k
a perfect model of each spring would reach on one record (:func:`perfect_sigma_k`). Over one
training set or several (modes and records at seeds of their own): the records inspected with one
training set share its modes' error, so its coverage alone says little of the designed rate.

    PYTHONPATH=. python bench/noisy_modes.py [records per cell] [samples per record] [training sets]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from harness.accelerometer import ALPHA, record, scenario
from harness.noisy_modes import SPRINGS, equation_error_modes, free_run_modes
from models.free_run_inspection import inspect_free_run
from models.inspection import inspect
from simulator.chain import ChainParameters


def driving_point(params: ChainParameters, frequencies: np.ndarray) -> np.ndarray:
    """The simulator's scheme from the force to mass 1's acceleration at ``frequencies`` (rad a
    sample): x[t+2] = A1·x[t+1] + A0·x[t] + e1·Ts²/m1·F[t], a[t] = (x[t+2] − 2x[t+1] + x[t])/Ts²."""
    A1, A0 = params.recursion()
    drive = np.zeros(params.n)
    drive[0] = params.ts**2 / params.masses[0]
    z = np.exp(1j * frequencies)
    return np.array(
        [
            (q - 1) ** 2 / params.ts**2 * np.linalg.solve(q * q * np.eye(params.n) - q * A1 - A0, drive)[0]
            for q in z
        ]
    )


def perfect_sigma_k(spring: str, samples: int) -> float:
    """σ_k [%] of a model that knew the chain exactly, on one record: the Cramér–Rao bound from
    the record's spectral (Whittle) information on k, the force white and the error the sensors'
    noise, σ²_y plus σ²_x through the structure: 1/σ²_k = N·mean_ω |∂G/∂k|²·σ²_F / (σ²_y + |G|²·σ²_x).
    No fault-mode model trained from noisy experiments does better."""
    healthy = scenario()
    frequencies = np.linspace(0, np.pi, 4097)[1:-1]
    response = driving_point(healthy.params, frequencies)
    step = 0.01  # percent: the response is linear in k far beyond
    slope = (driving_point(healthy.params.with_fault(spring, step), frequencies) - response) / step
    noise = healthy.y_noise_std**2 + np.abs(response) ** 2 * healthy.x_noise_std**2
    information = samples * np.mean(np.abs(slope) ** 2 * healthy.excitation_std**2 / noise)
    return float(1 / np.sqrt(information))


def main(count: int, samples: int, trainings: int) -> None:
    for spring in SPRINGS:
        print(
            f"a perfect model's sigma_k for {spring} on one record: {perfect_sigma_k(spring, samples):.3f} %"
        )
    for training in range(trainings):
        _one_training_set(count, samples, training)


def _one_training_set(count: int, samples: int, training: int) -> None:
    """The table for the modes of training set ``training`` (the first the tests' own), each
    training set's records at seeds of their own."""
    started = time.perf_counter()
    seed = 50_000 + 1000 * training
    chains = {
        "free run": (
            free_run_modes(seed=seed),
            lambda x, y, modes: inspect_free_run(x, y, modes, alpha=ALPHA),
        ),
        "paper": (equation_error_modes(seed=seed), lambda x, y, modes: inspect(x, y, modes, alpha=ALPHA)),
    }
    print(
        f"training set {training}: modes fitted in {time.perf_counter() - started:.1f} s; "
        f"{count} records of {samples} samples a cell"
    )
    print("chain     fault  k %   localised  covered  flagged  mean sigma_k  s/record")
    cells = [("none", 0.0)] + [(spring, k) for spring in SPRINGS for k in (4.0, 8.0, 12.0)]
    for name, (modes, chain) in chains.items():
        for cell, (fault, k) in enumerate(cells):
            clock = time.perf_counter()
            verdicts = [
                chain(
                    *record(scenario(fault, k), samples, 200_000 + 100_000 * training + 1000 * cell + i),
                    modes,
                )
                for i in range(count)
            ]
            spent = (time.perf_counter() - clock) / count
            localised = sum(v.status == "faulty" and v.fault_mode == fault for v in verdicts)
            covered = sum(v.interval is not None and v.interval[0] <= k <= v.interval[1] for v in verdicts)
            flagged = sum(v.fault_detected for v in verdicts)
            sigma = np.mean([v.sigma_k for v in verdicts if v.sigma_k is not None] or [np.nan])
            print(
                f"{name:8s}  {fault:5s}  {k:4.1f}  {localised:9d}  {covered:7d}  {flagged:7d}  "
                f"{sigma:12.3f}  {spent:8.2f}"
            )


if __name__ == "__main__":
    main(
        int(sys.argv[1]) if len(sys.argv) > 1 else 100,
        int(sys.argv[2]) if len(sys.argv) > 2 else 4000,
        int(sys.argv[3]) if len(sys.argv) > 3 else 1,
    )
