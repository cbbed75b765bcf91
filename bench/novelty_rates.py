"""False-alarm rate and power of baseline-only monitoring (models/novelty.py) over record lengths
and excitation levels unlike the training records', on the noisy 3-DOF accelerometer of
harness/accelerometer.py.

    PYTHONPATH=. python bench/novelty_rates.py [records per cell]
"""

from __future__ import annotations

import sys

import numpy as np

from harness.accelerometer import record, scenario
from models.narx import fit_narx
from models.novelty import judge_record, novelty_reference
from models.output_error import fit_output_error
from models.refinement import choose_linear


def main(count: int) -> None:
    training = [record(scenario(), 8000, 100 + i) for i in range(10)]
    _, terms = choose_linear(training, max_order=8)
    model = fit_output_error(fit_narx(training, terms), training, start_from="estimated").model
    reference = novelty_reference(model, training)
    print(
        f"reference: sigma2 {reference.sigma2:.4g}, {reference.rank} directions, "
        f"whitening order {len(reference.whitening)}, {reference.n_records} records"
    )
    print("level  length  flagged  rate   mean severity")
    for level in (0.5, 1.0, 2.0):
        healthy = scenario(level=level)
        for n in (1000, 2000, 4000, 8000, 16000):
            verdicts = [judge_record(model, reference, *record(healthy, n, 50_000 + i)) for i in range(count)]
            flagged = sum(v.status == "anomaly" for v in verdicts)
            severity = np.mean([v.severity for v in verdicts])
            print(f"{level:5.1f}  {n:6d}  {flagged:7d}  {flagged / count:.3f}  {severity:.4f}")
    # k3 barely reaches mass 1's acceleration: not expected
    for spring, loss in (("k1", 8.0), ("k2", 8.0), ("k3", 8.0), ("k1", 2.0), ("k1", 4.0)):
        faulty = scenario(spring, loss)
        verdicts = [judge_record(model, reference, *record(faulty, 4000, 60_000 + i)) for i in range(count)]
        flagged = sum(v.status == "anomaly" for v in verdicts)
        print(f"{loss:.0f} % loss of {spring}, 4000 samples: {flagged}/{count} flagged")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 200)
