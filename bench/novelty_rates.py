"""False-alarm rate and power of baseline-only monitoring (models/novelty.py) on the noisy 3-DOF
accelerometer of harness/accelerometer.py, for baselines trained as the service trains one
without given terms: ten healthy records, their terms chosen by
:func:`models.baseline_choice.choose_baseline_terms`, fitted by output error from the estimated
start. Each training length's baseline judges healthy records of several lengths and
excitation levels, and records of a loosened spring.

    PYTHONPATH=. python bench/novelty_rates.py [records per cell] [training samples …]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from harness.accelerometer import ALPHA, record, scenario
from models.baseline_choice import choose_baseline_terms
from models.narx import NARX, fit_narx
from models.novelty import NoveltyReference, NoveltyVerdict, judge_record, novelty_reference
from models.output_error import fit_output_error
from simulator.chain import ChainScenario

TRAINING = (600, 2000)
LENGTHS = (600, 2000)
LEVELS = (0.5, 1.0, 2.0)
# k3 barely reaches mass 1's acceleration: not expected
FAULTS = (("k1", 8.0), ("k2", 8.0))


def judged(
    model: NARX, reference: NoveltyReference, s: ChainScenario, n: int, count: int, seed: int
) -> list[NoveltyVerdict]:
    return [judge_record(model, reference, *record(s, n, seed + i), alpha=ALPHA) for i in range(count)]


def main(count: int, training_lengths: tuple[int, ...]) -> None:
    for samples in training_lengths:
        training = [record(scenario(), samples, 100 + i) for i in range(10)]
        started = time.perf_counter()
        choice = choose_baseline_terms(training)
        chosen = time.perf_counter()
        model = fit_narx(training, list(choice.terms))
        model = fit_output_error(model, training, start_from="estimated").model
        fitted = time.perf_counter()
        reference = novelty_reference(model, training)
        referenced = time.perf_counter()
        largest = float(np.linalg.eigvalsh(reference.covariance)[-1])
        print(
            f"training 10 x {samples}: ARX({choice.ny}, {choice.nx}) delay {choice.delay}, "
            f"{len(choice.added)} nonlinear terms; {reference.rank} directions, largest eigenvalue of C "
            f"{largest:.2f}; choice {chosen - started:.1f} s, fit {fitted - chosen:.1f} s, "
            f"reference {referenced - fitted:.1f} s"
        )
        print("  level  length  flagged  rate   mean severity")
        for level in LEVELS:
            healthy = scenario(level=level)
            for n in LENGTHS if level == 1.0 else LENGTHS[-1:]:
                verdicts = judged(model, reference, healthy, n, count, 50_000)
                flagged = sum(v.status == "anomaly" for v in verdicts)
                severity = np.mean([v.severity for v in verdicts])
                print(f"  {level:5.1f}  {n:6d}  {flagged:7d}  {flagged / count:.3f}  {severity:.4f}")
        for spring, loss in FAULTS:
            faulty = scenario(spring, loss)
            for n in LENGTHS:
                verdicts = judged(model, reference, faulty, n, count, 60_000)
                flagged = sum(v.status == "anomaly" for v in verdicts)
                print(f"  {loss:.0f} % loss of {spring}, {n} samples: {flagged}/{count} flagged")


if __name__ == "__main__":
    main(
        int(sys.argv[1]) if len(sys.argv) > 1 else 200,
        tuple(int(v) for v in sys.argv[2:]) or TRAINING,
    )
