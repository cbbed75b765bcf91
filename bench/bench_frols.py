"""FROLS structure selection against SysIdentPy 0.9.0, in one process on the same data.

    make bench      # builds .venv-bench with the `bench` extra (SysIdentPy) and runs this there

SysIdentPy 0.9.0 caps numpy at 2.3.5, so it gets its own environment (.venv-bench) rather than
downgrading the one narxwatch runs and is tested in.

Data: the paper's healthy 2-DOF structure as the study simulates it (SPEC §6: white force
excitation of std 25 kN, unmeasured force disturbance of 800 N), 30 000 samples for selection
and 30 000 more, from another seed, held out. Candidates: degree 3 in y[t-1 … t-4] and
x[t-1 … t-4] with the constant, 165 in all (SysIdentPy's ylag = xlag = 4, Polynomial(degree=3)).

1. A fixed 15 terms: ``select_narx(n_terms=15)`` against ``FROLS(order_selection=False,
   n_terms=15, estimator=LeastSquares())``.
2. BIC over up to 15 terms: ``select_narx(criterion="bic", max_terms=15)`` (one greedy path)
   against ``FROLS(order_selection=True, n_info_values=15, info_criteria="bic")`` (which
   re-runs the path for every model size).

Both timings cover the whole fit: candidate matrix, selection and parameter estimation. The
script prints both times (best of several runs), their ratio, both held-out one-step RMS
errors, whether the first 10 terms agree (a difference is accepted only where the two ERR
values differ by less than 1e-10), and the peak resident memory of our selection measured in
a fresh process (VmHWM). It exits with status 1 if the terms disagree or a target is missed.
"""

from __future__ import annotations

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from importlib.metadata import version
from itertools import combinations_with_replacement
from typing import Any

import numpy as np

from models.candidates import candidate_terms
from models.selection import select_narx
from models.terms import Factor, Term
from models.validation import validate
from simulator.simulate import simulate
from simulator.study import StudySettings

SAMPLES = 30_000
SEED, HELD_OUT_SEED = 30_000, 30_001
TERMS, COMPARED = 15, 10
TARGET_FIXED, TARGET_CRITERION, TARGET_MB = 10.0, 50.0, 300.0
ERR_TIE = 1e-10


def best_time(run: Callable[[], Any], repeats: int) -> tuple[float, float, Any]:
    """Best and median wall time in seconds over ``repeats`` runs, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        times.append(time.perf_counter() - start)
    return min(times), float(np.median(times)), result


def sysidentpy_terms(pivots: np.ndarray) -> list[Term]:
    """SysIdentPy's regressor index → term: combinations of degree 3 over the lagged columns
    (1, y[k-1] … y[k-4], x[k-1] … x[k-4]), padded with the constant column 0."""
    variables: list[Factor | None] = [None, *(Factor("y", i) for i in range(1, 5))]
    variables += [Factor("x", i) for i in range(1, 5)]
    combos = list(combinations_with_replacement(range(9), 3))
    return [Term.of(variables[c] for c in combos[p] if variables[c] is not None) for p in pivots]


def agreement(ours: Any, theirs: Any) -> tuple[bool, list[str]]:
    """The first COMPARED terms (or as many as SysIdentPy kept): equal, or their ERR values
    (SysIdentPy's less the eps it adds to each) differ by less than ERR_TIE."""
    count = min(COMPARED, len(theirs.pivv))
    mine = ours.path_terms[:count]
    other = sysidentpy_terms(theirs.pivv[:count])
    their_err = np.asarray(theirs.err[:count]) - np.finfo(np.float64).eps
    rows, ok = [], True
    for k in range(count):
        difference = abs(ours.path.err[k] - their_err[k])
        same = mine[k] == other[k]
        ok &= same or difference < ERR_TIE
        mark = "=" if same else ("tie" if difference < ERR_TIE else "DIFFERENT")
        rows.append(
            f"  {k + 1:>2} {mine[k].name:<22} {other[k].name:<22} {ours.path.err[k]:.6e} "
            f"{their_err[k]:.6e} {difference:.1e} {mark}"
        )
    return ok, rows


def sysidentpy_one_step_rms(model: Any, x: np.ndarray, y: np.ndarray) -> float:
    predicted = model.predict(X=x.reshape(-1, 1), y=y.reshape(-1, 1), steps_ahead=1).ravel()
    return float(np.sqrt(np.mean((y[4:] - predicted[4:]) ** 2)))


def peak_memory_mb() -> tuple[float, float]:
    """Peak resident memory (VmHWM, Linux) of a fresh process: after simulating the record, and
    after both selections. (getrusage's ru_maxrss would report this process's size instead: Linux
    carries the parent's high-water mark across fork and exec.)"""
    script = textwrap.dedent(
        f"""
        import service
        from models.candidates import candidate_terms
        from models.selection import select_narx
        from simulator.study import StudySettings
        from simulator.simulate import simulate
        def peak():
            with open("/proc/self/status") as status:
                return next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
        rec = simulate(StudySettings().scenario(), {SAMPLES}, {SEED})
        before = peak()
        select_narx([(rec.x, rec.y)], candidate_terms(), n_terms={TERMS})
        select_narx([(rec.x, rec.y)], candidate_terms(), criterion="bic", max_terms={TERMS})
        print(before, peak())
        """
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    before, after = (int(value) / 1024 for value in result.stdout.split())
    return before, after


def main() -> int:
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.model_structure_selection import FROLS
    from sysidentpy.parameter_estimation.estimators import LeastSquares

    settings = StudySettings()
    record = simulate(settings.scenario(), SAMPLES, SEED)
    held = simulate(settings.scenario(), SAMPLES, HELD_OUT_SEED)
    candidates = candidate_terms()
    data = [(record.x, record.y)]
    X, Y = record.x.reshape(-1, 1), record.y.reshape(-1, 1)

    def theirs(**options: Any) -> Any:
        model = FROLS(
            ylag=4, xlag=4, basis_function=Polynomial(degree=3), estimator=LeastSquares(), **options
        )
        return model.fit(X=X, y=Y)

    print(
        f"numpy {np.__version__}, scipy {version('scipy')}, sysidentpy {version('sysidentpy')}; "
        f"{SAMPLES} samples (study scenario: 25 kN excitation, 800 N disturbance, seed {SEED}), "
        f"{len(candidates)} candidates, held-out record seed {HELD_OUT_SEED}"
    )
    results, ok = [], True
    cases = [
        (
            f"fixed {TERMS} terms",
            lambda: select_narx(data, candidates, n_terms=TERMS),
            lambda: theirs(order_selection=False, n_terms=TERMS),
            3,
            TARGET_FIXED,
        ),
        (
            f"BIC, up to {TERMS} terms",
            lambda: select_narx(data, candidates, criterion="bic", max_terms=TERMS),
            lambda: theirs(order_selection=True, n_info_values=TERMS, info_criteria="bic"),
            1,
            TARGET_CRITERION,
        ),
    ]
    for label, ours_run, theirs_run, their_repeats, target in cases:
        ours_run()  # warm-up: first-touch page faults and imports are not the algorithm
        our_best, our_median, ours = best_time(ours_run, 7)
        their_best, their_median, other = best_time(theirs_run, their_repeats)
        ratio = their_best / our_best
        our_error = validate(ours.model, [(held.x, held.y)]).one_step.rms
        their_error = sysidentpy_one_step_rms(other, held.x, held.y)
        agree, rows = agreement(ours, other)
        ok &= agree and ratio >= target
        results.append((label, our_best, our_median, their_best, their_median, ratio, target, ours, other,
                        our_error, their_error, agree, rows))  # fmt: skip

    print()
    print(
        "| selection | ours best (median) | SysIdentPy best (median) | speed-up | target "
        "| terms ours / SysIdentPy | held-out one-step RMS ours / SysIdentPy | path terms |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for label, ob, om, tb, tm, ratio, target, ours, other, oe, te, agree, _ in results:
        print(
            f"| {label} | {1e3 * ob:.1f} ms ({1e3 * om:.1f}) | {tb:.2f} s ({tm:.2f}) | {ratio:.0f}× "
            f"| ≥ {target:.0f}× "
            f"| {len(ours.model.terms)} / {len(other.final_model)} | {oe:.4e} / {te:.4e} m "
            f"| {'agree' if agree else 'DISAGREE'} |"
        )
    for label, *_, rows in results:
        print(f"\n{label}: step, our term, SysIdentPy's term, our ERR, SysIdentPy's ERR − eps, |difference|")
        print("\n".join(rows))
    before, after = peak_memory_mb()
    ok &= after < TARGET_MB
    print(
        f"\npeak resident memory (VmHWM) of a fresh process: {before:.0f} MB after simulating, "
        f"{after:.0f} MB after both selections (limit {TARGET_MB:.0f} MB)"
    )
    print("all targets met" if ok else "A TARGET IS MISSED OR THE TERMS DISAGREE")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
