"""Fault modes under sensor noise (models/free_run_inspection.py) against the paper's chain
(models/inspection.py), on the noisy 3-DOF accelerometer of harness/accelerometer.py: per fault
and magnitude, how often each localises the fault, how often its interval covers the truth, its
mean σ̂_k; and the healthy records' false alarms. First, what the record itself allows: the σ_k
a perfect model of each spring would reach on one record
(:func:`harness.noisy_modes.perfect_sigma_k`). Over one training set or several (modes and
records at seeds of their own): the records inspected with one training set share its modes'
error, so its coverage alone says little of the designed rate.

    PYTHONPATH=. python bench/noisy_modes.py [records per cell] [samples per record] [training sets]

Second, how the far spring's mode depends on its training design (:func:`designs`): per design
and training set, its slope against the chain's, its held-out scale, and per magnitude how often
its own interval (k̂ ± z·σ̂_k from the verdict's ``modes``, given or withheld) covers the truth.

    PYTHONPATH=. python bench/noisy_modes.py designs [records per cell] [samples per record] \
        [training sets] [design …]

Third, whether the near spring's interval is biased or too narrow anywhere in its range
(:func:`near`): over many training sets, per magnitude, k̂'s mean miss, its spread within a
training set against σ̂_k,record and the spread of the training sets' mean k̂ against the mode's
own part of σ̂_k.

    PYTHONPATH=. python bench/noisy_modes.py near [records per cell] [samples per record] \
        [training sets]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from harness.accelerometer import ALPHA, record, scenario
from harness.noisy_modes import (
    FAR_MAGNITUDES,
    MAGNITUDES,
    SPRINGS,
    equation_error_modes,
    free_run_modes,
    perfect_sigma_k,
    slope_against_truth,
)
from models.free_run_inspection import inspect_free_run
from models.inspection import inspect
from models.narx import z_quantile

# The far spring's training designs (:func:`designs`): free_run_modes's arguments.
STEPS = tuple(2.5 * i for i in range(7))  # 0, 2.5 … 15 %
DESIGNS = {
    "4x1x8000": {},
    "4x1x8000-alone": {"springs": ("k3",)},
    "7x1x8000-alone": {"springs": ("k3",), "magnitudes": STEPS},
    "4x3x8000-alone": {"springs": ("k3",), "repeats": 3},
    "4x1x32000-alone": {"springs": ("k3",), "samples": 32_000},
    "0-30-alone": {"springs": ("k3",), "magnitudes": (0.0, 10.0, 20.0, 30.0)},
    "0-45-alone": {"springs": ("k3",), "magnitudes": FAR_MAGNITUDES},
    "0-45": {"magnitudes": {"k2": MAGNITUDES, "k3": FAR_MAGNITUDES}},
    "4x3x8000": {"repeats": 3},
    "4x1x32000": {"samples": 32_000},
}


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


def designs(count: int, samples: int, trainings: int, names: list[str]) -> None:
    """The far spring's mode per training design (DESIGNS): for each training set its slope
    against the chain's (:func:`slope_against_truth`) and its held-out scale c; per magnitude,
    over the training sets' records, n, how often k3 is localised and how often the mode's own
    interval covers the truth, with the mean k̂ and σ̂_k."""
    z = z_quantile(1 - ALPHA)
    for name in names:
        print(f"design {name}: {DESIGNS[name]}")
        cells: dict[float, list] = {}
        for training in range(trainings):
            clock = time.process_time()
            modes = free_run_modes(seed=60_000 + 1000 * training, **DESIGNS[name])
            far = next(mode for mode in modes if mode.name == "k3")
            along, across, misfit = slope_against_truth(far)
            print(
                f"  set {training}: c {far.scale:.2f}, slope along the chain's {along:.2f}, "
                f"across {across:.2f}, healthy misfit {misfit:.3f} m/s^2, "
                f"fit {time.process_time() - clock:.0f} CPU s"
            )
            for cell, k in enumerate((0.0, 4.0, 8.0, 12.0)):
                fault = "k3" if k else "none"
                for i in range(count):
                    x, y = record(scenario(fault, k), samples, 300_000 + 100_000 * training + 1000 * cell + i)
                    cells.setdefault(k, []).append(inspect_free_run(x, y, modes, alpha=ALPHA))
        print("  k %   n  localised  covered  mean k_hat  mean sigma_k")
        for k, verdicts in cells.items():
            far_modes = [v.mode("k3") for v in verdicts]
            localised = sum(v.status == "faulty" and v.fault_mode == "k3" for v in verdicts)
            covered = sum(abs(m.k_hat - k) <= z * m.sigma_k for m in far_modes)
            k_hat, sigma_k = (np.mean([getattr(m, key) for m in far_modes]) for key in ("k_hat", "sigma_k"))
            print(
                f"  {k:4.1f}  {len(verdicts):3d}  {localised:9d}  {covered:7d}  "
                f"{k_hat:10.2f}  {sigma_k:12.2f}"
            )


# The near spring's magnitudes (:func:`near`): its range's ends, where k̂ is held within the
# range, and the watched magnitudes between.
NEAR_MAGNITUDES = (0.0, 4.0, 8.0, 12.0, 15.0)


def near(count: int, samples: int, trainings: int) -> None:
    """The near spring's interval over ``trainings`` training sets (modes from seeds 50 000,
    51 000, …; records at seeds of their own), ``count`` records a training set and magnitude.

    Per magnitude, pooled: how often k2 is localised, how often the verdict's interval and the
    mode's own (k̂ ± z·σ̂_k, given or not) cover the truth; k̂'s mean miss with its standard
    error (the training sets' means scatter by the modes' error); k̂'s spread within a training
    set against the mean σ̂_k,record (the records' own error); the spread of the training sets'
    mean k̂, less what their records' own error gives it, against the mean of the mode's own part
    √(σ̂²_k − σ̂²_k,record).
    """
    z = z_quantile(1 - ALPHA)
    print(f"a perfect model's sigma_k for k2 on one record: {perfect_sigma_k('k2', samples):.3f} %")
    cells: dict[float, list[tuple[int, float, float, float, bool, bool]]] = {}
    for training in range(trainings):
        clock = time.process_time()
        modes = free_run_modes(seed=50_000 + 1000 * training)
        for cell, k in enumerate(NEAR_MAGNITUDES):
            for i in range(count):
                seed = 5_000_000 + 100_000 * training + 1000 * cell + i
                verdict = inspect_free_run(
                    *record(scenario("k2" if k else "none", k), samples, seed), modes, alpha=ALPHA
                )
                mode = verdict.mode("k2")
                localised = verdict.status == "faulty" and verdict.fault_mode == "k2"
                covered = localised and verdict.interval[0] <= k <= verdict.interval[1]
                cells.setdefault(k, []).append(
                    (training, mode.k_hat - k, mode.sigma_k, mode.sigma_k_record, localised, covered)
                )
        print(f"training set {training}: c {modes[0].scale:.2f}, {time.process_time() - clock:.0f} CPU s")
    print(
        "  k %    n  localised  covered  own covers  mean miss (s.e.)  spread within  sigma_k,record"
        "  sets' spread  mode's part"
    )
    for k, rows in cells.items():
        sets, miss, sigma, own, localised, covered = (np.array(column) for column in zip(*rows, strict=True))
        means = np.array([miss[sets == t].mean() for t in range(trainings)])
        within = float(np.sqrt(np.mean([miss[sets == t].var(ddof=1) for t in range(trainings)])))
        between = float(np.sqrt(max(means.var(ddof=1) - within**2 / count, 0.0)))
        mode_part = float(np.mean(np.sqrt(np.maximum(sigma**2 - own**2, 0.0))))
        error = means.std(ddof=1) / np.sqrt(trainings)
        print(
            f"  {k:4.1f}  {miss.size:4d}  {localised.sum():9d}  {covered.sum():7d}  "
            f"{np.sum(np.abs(miss) <= z * sigma):10d}  {miss.mean():+9.3f} ({error:.3f})"
            f"  {within:13.3f}  {own.mean():14.3f}  {between:12.3f}  {mode_part:11.3f}"
        )


if __name__ == "__main__" and sys.argv[1:2] == ["near"]:
    numbers = [int(a) for a in sys.argv[2:5]]
    near(*(numbers + [30, 4000, 12][len(numbers) :]))
elif __name__ == "__main__" and sys.argv[1:2] == ["designs"]:
    numbers = [int(a) for a in sys.argv[2:5]]
    designs(*(numbers + [15, 4000, 3][len(numbers) :]), sys.argv[5:] or list(DESIGNS))
elif __name__ == "__main__":
    main(
        int(sys.argv[1]) if len(sys.argv) > 1 else 100,
        int(sys.argv[2]) if len(sys.argv) > 2 else 4000,
        int(sys.argv[3]) if len(sys.argv) > 3 else 1,
    )
