"""Fault modes under sensor noise (models/free_run_inspection.py) against the paper's chain
(models/inspection.py), on the noisy 3-DOF accelerometer of harness/accelerometer.py: per fault
and magnitude, how often each localises the fault, how often its interval covers the truth, its
mean σ̂_k; and the healthy records' false alarms. First, what the record itself allows: the σ_k
a perfect model of each spring would reach on one record
(:func:`harness.noisy_modes.perfect_sigma_k`). Over one training set or several (modes and
records at seeds of their own): the records inspected with one training set share its modes'
error, so its coverage alone says little of the designed rate.

    PYTHONPATH=. python bench/noisy_modes.py [records per cell] [samples per record] [training sets]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from harness.accelerometer import ALPHA, record, scenario
from harness.noisy_modes import SPRINGS, equation_error_modes, free_run_modes, perfect_sigma_k
from models.free_run_inspection import inspect_free_run
from models.inspection import inspect


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
