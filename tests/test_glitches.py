"""Glitches: samples so far out that they are more likely a sensor's fault than response
(``models.signals.glitches``), and the refinement report's note naming them."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io

from harness.prerequisites import benchmark_file
from models.refinement import GLITCHES_NAMED, _glitch_notes, refine_records
from models.signals import GLITCH_FACTOR, glitches
from recordfiles.reader import parse_silverbox
from simulator.simulate import Scenario, simulate


def measured_signals() -> dict[str, np.ndarray]:
    """Inputs and outputs of the three benchmarks in ../shared/data, none developed on here."""
    silverbox = parse_silverbox(benchmark_file("silverbox", "SNLS80mV.csv").read_bytes())
    sweep = scipy.io.loadmat(benchmark_file("f16-gvt", "F16Data_SineSw_Level7.mat"))
    wh = benchmark_file("wiener-hammerstein", "WH_EstimationExample.csv")
    wiener = np.genfromtxt(wh, delimiter=",")[1:]
    signals = {"Silverbox V1": silverbox.x, "Silverbox V2": silverbox.y, "F-16 force": sweep["Force"].ravel()}
    signals |= {f"F-16 acceleration {k + 1}": sweep["Acceleration"][k] for k in range(3)}
    # Columns r×10, u×10, y×10, fs: the ten measured inputs and outputs.
    signals |= {f"Wiener–Hammerstein column {k}": wiener[:, k] for k in range(10, 30)}
    return signals


def test_measured_signals_hold_none_and_a_sample_at_ten_times_the_largest_is_found():
    signals = measured_signals()
    assert len(signals) == 26
    for name, values in signals.items():
        assert glitches(values).size == 0, name
        glitched = values.copy()
        glitched[len(values) // 3] = 10 * np.abs(values).max()
        assert glitches(glitched).tolist() == [len(values) // 3], name


def test_gaussian_and_laplacian_noise_hold_none_and_the_rule_is_the_percentile_times_the_factor():
    rng = np.random.default_rng(7)
    for values in (rng.normal(3.0, 2.0, 1_000_000), rng.laplace(-1.0, 0.5, 1_000_000)):
        assert glitches(values).size == 0
    values = rng.normal(0.0, 1.0, 10_000)
    spread = np.quantile(np.abs(values - np.median(values)), 0.99)
    # A fifth either side of the bound: setting three samples moves the percentile far less.
    values[[10, 20, 30]] = np.median(values) + GLITCH_FACTOR * spread * np.array([1.2, -1.2, 0.8])
    assert glitches(values).tolist() == [10, 20]
    assert glitches(np.zeros(100)).size == 0


# Glitches are found in the estimation records alone, whatever the loop makes of them: the report
# is tested once for its notes (the names, the records, the cure), the notes' content where they are
# made (models.refinement._glitch_notes), on records of the length the rule needs, not the loop.
# Clean records of 1500 samples reach 1.4 times the 99th percentile's spread, far below the factor.
def simulated(seed: int, samples: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    record = simulate(Scenario(disturbance_std=20.0), samples, seed)
    return record.x, record.y.copy()


def numbered(signal: str, record: int, index: int) -> str:
    """A sample as the report names it in one record."""
    return f"{signal}[{index}]"


def test_the_report_names_each_glitch_by_its_signal_record_and_sample():
    records = [simulated(seed) for seed in (5, 6)]
    (x1, y1), (x2, y2) = records
    glitched_x, glitched_y = x1.copy(), y2.copy()
    glitched_x[321] = 10 * np.abs(x1).max()
    glitched_y[1234] = 10 * np.abs(y2).max()
    declared = ["y[t-1]", "y[t-2]", "x[t-1]"]
    report = refine_records([(glitched_x, y1), (x2, glitched_y)], [(x1, y1)], declared, initial=2)
    on_x, on_y = [note for note in report.notes if "as a glitch does" in note]
    assert on_x.startswith(f"x[321] of record 1 = {glitched_x[321]:.4g} lies more than 6 times as far")
    assert "median input" in on_x
    assert on_y.startswith(f"y[1234] of record 2 = {glitched_y[1234]:.4g} lies more than 6 times as far")
    assert "median output" in on_y and on_y.endswith("if it is one, cut it out of its record")
    assert _glitch_notes(records, numbered, "cut it out of its record") == ()


@pytest.mark.parametrize("count", [5, 7])
def test_five_glitches_are_named_and_the_rest_counted(count: int):
    x, y = simulated(8, 3000)
    y[100 : 100 + 10 * count : 10] = 10 * np.abs(y).max()
    (note,) = _glitch_notes([(x, y)], numbered, "cut it out of its record")
    assert note.count("y[") == GLITCHES_NAMED == 5 and ("and 2 more samples lie more" in note) == (count == 7)
