"""The held-out gate's level on one free run over a short tail, computed (docs/benchmarks/planted.md,
"The held-out gate on short tails").

    .venv/bin/python -m bench.held_out_level [--draws 4000] [--samples 316]

Two models equally good over a tail: their free-run errors independent draws of one process, white
or a lightly damped resonance (pole radius 0.9, 0.97 and 0.99 at 0.01 cycles a sample, over about
a block's length or more, as the rig's free-run errors are), each built up from zero over the
tail's first ``COMPARISON_SAMPLES`` as a free run's error is from the measured outputs it starts
on (the same envelope for both). For each, the share of draws in which the refined model passes
at 0.025, one-sided:

- ``blocks``: the mean of the blocks' log ratios of mean squares over its standard error as
  Student's t, every block counted (the gate without its warm-up);
- ``warm-up``: the same past the warm-up (:func:`models.held_out.one_run_comparison`, the gate);
- ``DM–NW m``: Diebold and Mariano's test on the per-sample log ratios of squared errors, their
  mean's variance by Newey and West's estimator (statsmodels' HAC) with m lags, as the normal.

Seeds are fixed: a rerun prints the same figures.
"""

from __future__ import annotations

import argparse

import numpy as np
import scipy.signal
import scipy.stats
import statsmodels.api as sm

from models.held_out import COMPARISON_SAMPLES, _block_squares, _paired, one_run_comparison

LEVEL = 0.025
RADII = (0.0, 0.9, 0.97, 0.99)  # 0: white errors
CYCLES = 0.01  # the resonance's frequency, cycles a sample
BURN_IN = 3000
HAC_LAGS = (5, 20, 50)


def errors(rng: np.random.Generator, radius: float, samples: int) -> np.ndarray:
    """Two independent error series of ``samples``, white or through the resonance of pole
    ``radius``, each built up from zero over the first ``COMPARISON_SAMPLES``."""
    white = rng.standard_normal((2, samples + BURN_IN))
    if radius:
        angle = 2 * np.pi * CYCLES
        white = scipy.signal.lfilter([1.0], [1.0, -2 * radius * np.cos(angle), radius**2], white, axis=1)
    envelope = np.minimum(1.0, np.arange(samples) / COMPARISON_SAMPLES)
    return envelope * white[:, BURN_IN:]


def diebold_mariano(start: np.ndarray, refined: np.ndarray, lags: int) -> float:
    """The t statistic of the per-sample log ratios' mean, its variance Newey–West's with ``lags``."""
    ratio = np.log(np.maximum(start**2, 1e-300)) - np.log(np.maximum(refined**2, 1e-300))
    fit = sm.OLS(ratio, np.ones_like(ratio)).fit(cov_type="HAC", cov_kwds={"maxlags": lags})
    return float(fit.tvalues[0])


def passes(rng: np.random.Generator, radius: float, samples: int) -> dict[str, bool]:
    start, refined = errors(rng, radius, samples)
    blocks = int(np.clip(samples // COMPARISON_SAMPLES, 3, 20))
    gain, threshold = _paired(_block_squares([start], blocks), _block_squares([refined], blocks), LEVEL)
    warm_gain, warm_threshold = one_run_comparison([start], [refined], LEVEL)
    quantile = scipy.stats.norm.ppf(1 - LEVEL)
    return {
        "blocks": gain > threshold,
        "warm-up": warm_gain > warm_threshold,
        **{f"DM–NW {lags}": diebold_mariano(start, refined, lags) > quantile for lags in HAC_LAGS},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--draws", type=int, default=4000)
    parser.add_argument("--samples", type=int, default=316, help="errors over the tail (320 less 4 lags)")
    arguments = parser.parse_args()
    rng = np.random.default_rng(2024)
    for radius in RADII:
        counts: dict[str, int] = {}
        for _ in range(arguments.draws):
            for name, passed in passes(rng, radius, arguments.samples).items():
                counts[name] = counts.get(name, 0) + passed
        shares = "  ".join(f"{name} {count / arguments.draws:.4f}" for name, count in counts.items())
        print(f"pole radius {radius:g}: {shares}", flush=True)


if __name__ == "__main__":
    main()
