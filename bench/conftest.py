"""Shared data for the speed benchmarks: everything here is built once per session, untimed.

The settings follow the issue's speed targets (and SPEC §4–§6): fault-mode models are trained
on 17 experiments k = −32, −28, …, 32 of 2000 samples each, simulated with a 25 kN white force
and an 800 N unmeasured force disturbance; the baseline NARX and the simulator work on 30 000
samples. Seeds are fixed so every run times the same arithmetic.

Run with ``.venv/bin/pytest bench --benchmark-only`` (or ``make bench``). The files are named
``test_bench_*.py``, which pytest's default ``python_files`` collects when ``bench`` is named
on the command line; ``pytest`` alone still runs only ``tests`` (pyproject's ``testpaths``).
Fixtures only: nothing imports from this module, and ``bench/__init__.py`` keeps it from being
confused with ``tests/conftest.py``.
"""

from __future__ import annotations

from collections.abc import Callable

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import numpy as np
import pytest

from models.fnarx import FNARX, fit_fnarx
from simulator.simulate import Scenario, SimulatedRecord, simulate
from simulator.theory import EXACT_TERMS

EXCITATION_STD = 25e3  # N
DISTURBANCE_STD = 800.0  # N
EXPERIMENT_SAMPLES = 2000
MAGNITUDES = tuple(float(k) for k in range(-32, 33, 4))  # 17 experiments
FAULT_MODES = ("k2", "k1")
LONG_SAMPLES = 30_000

# Seed blocks kept apart so training, inspection and long records never share noise.
_TRAINING_SEED = {"k2": 10_000, "k1": 20_000}
LONG_RECORD_SEED = 30_000


def scenario(fault: str = "none", k: float = 0.0) -> Scenario:
    return Scenario(fault=fault, k=k, excitation_std=EXCITATION_STD, disturbance_std=DISTURBANCE_STD)


Experiments = list[tuple[np.ndarray, np.ndarray, float]]
RecordFactory = Callable[[str, float, int, int], SimulatedRecord]


@pytest.fixture(scope="session")
def make_record() -> RecordFactory:
    """``make_record(fault, k, n, seed)``: a record simulated with the benchmarks' excitation and noise."""

    def factory(fault: str, k: float, n: int, seed: int) -> SimulatedRecord:
        return simulate(scenario(fault, k), n, seed)

    return factory


@pytest.fixture(scope="session")
def training_experiments() -> dict[str, Experiments]:
    """Per fault mode, the 17 × 2000-sample experiments (x, y, k) an FNARX model is fitted on."""
    experiments: dict[str, Experiments] = {}
    for mode in FAULT_MODES:
        runs = []
        for index, k in enumerate(MAGNITUDES):
            record = simulate(scenario(mode, k), EXPERIMENT_SAMPLES, _TRAINING_SEED[mode] + index)
            runs.append((record.x, record.y, k))
        experiments[mode] = runs
    return experiments


@pytest.fixture(scope="session")
def fault_models(training_experiments: dict[str, Experiments]) -> list[FNARX]:
    """The two fault-mode models, k2 then k1, the inspection chain tests a record against."""
    return [fit_fnarx(training_experiments[mode], EXACT_TERMS, name=mode) for mode in FAULT_MODES]


@pytest.fixture(scope="session")
def long_record() -> SimulatedRecord:
    """A healthy 30 000-sample record (the paper's N for the baseline identification)."""
    return simulate(scenario(), LONG_SAMPLES, LONG_RECORD_SEED)
