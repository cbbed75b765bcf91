"""Target 2: FNARX training, fit_fnarx on 17 experiments × 2000 samples ≤ 100 ms.

The experiments are simulated once per session (conftest); only the fit is timed.
"""

from __future__ import annotations

import numpy as np
import pytest

from models.fnarx import fit_fnarx
from simulator.physics import PhysicalParameters
from simulator.theory import EXACT_TERMS, exact_coefficients

MODES = ["k2", "k1"]


@pytest.mark.benchmark(group="fit_fnarx: 17 x 2000 samples (target <= 100 ms)")
@pytest.mark.parametrize("mode", MODES)
def test_fit_fnarx_17_experiments(benchmark, training_experiments, mode: str) -> None:
    experiments = training_experiments[mode]
    benchmark.extra_info["target_median_ms"] = 100.0

    model = benchmark(fit_fnarx, experiments, EXACT_TERMS, name=mode)

    n_terms = len(EXACT_TERMS)
    assert len(experiments) == 17
    assert model.theta.shape == (n_terms, 2)
    assert model.n_obs == sum(len(y) - model.max_lag for _, y, _ in experiments)
    # At k = 0 the model is the healthy structure: its AR part must match the exact NARX closely.
    healthy = exact_coefficients(PhysicalParameters())
    np.testing.assert_allclose(model.coefficients(0.0)[:4], healthy[:4], atol=1e-3)
