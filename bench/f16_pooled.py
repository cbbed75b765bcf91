"""F-16 ground vibration test: the three accelerations as one vector model pooled over the level.

    .venv/bin/python -m bench.f16_pooled [--lags 10] [--plot var/f16_modes.png]

The benchmark's split (shared/data/f16-gvt, README there): estimation on the sine sweeps of
levels 3, 5 and 7, test on levels 2, 4 and 6. A vector model of the three accelerations
(:mod:`models.vector`, every channel's lags, ``--lags`` of them), its coefficients affine in the
record's excitation level — the force's standard deviation [N] in the role of the magnitude k —
is fitted on the three estimation levels together by least squares, and run free on each test
record at that record's level. Beside it, a separate model for each estimation level (the same
structure, one level's data), run on each test record from the nearest level. Then the natural
frequencies and damping ratios of the pooled model's dynamics at every level 1 … 7, as a table
and a plot (the benchmark's authors ask for frequency and damping against level).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from models.blas import one_blas_thread

one_blas_thread()  # before numpy is imported: one BLAS thread, as in narxwatch's processes
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from harness.prerequisites import DATA_DIR
from models.vector import fit_vector_fnarx, modal_parameters, simulate_vector
from recordfiles.reader import Layout, read_record

ESTIMATION, TEST = (3, 5, 7), (2, 4, 6)
MAX_DAMPING = 0.2  # poles more damped than this are not reported as modes
BAND = (1.0, 100.0)  # Hz


def level(number: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Force [N], the three accelerations [m/s²] as (N, 3), and the rate [Hz] of a level's sweep."""
    suffix = "_Validation" if number in TEST else ""
    path = DATA_DIR / "f16-gvt" / f"F16Data_SineSw_Level{number}{suffix}.mat"
    channels = [read_record(path, Layout("Force", f"Acceleration{o}")) for o in (1, 2, 3)]
    return channels[0].x, np.column_stack([c.y for c in channels]), float(channels[0].fs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lags", type=int, default=10, help="lags of every channel and of the force")
    parser.add_argument(
        "--plot", type=Path, default=Path("var/f16_modes.png"), help="PNG of f and ζ against level"
    )
    arguments = parser.parse_args()
    records = {n: level(n) for n in range(1, 8)}
    amplitude = {n: float(np.std(x)) for n, (x, _, _) in records.items()}
    fs = records[3][2]
    pooled = fit_vector_fnarx(
        "level", [(records[n][0], records[n][1], amplitude[n]) for n in ESTIMATION], lags=arguments.lags
    )
    separate = {
        n: fit_vector_fnarx(
            f"level {n}", [(*records[n][:2], 0.0), (*records[n][:2], 1.0)], lags=arguments.lags, basis_size=1
        )
        for n in ESTIMATION
    }
    print(f"Free-run RMS on the test levels [m/s²] (vector model of lags {arguments.lags}, least squares)")
    print("level  force std   pooled (acc 1, 2, 3)          separate, nearest level (acc 1, 2, 3)")
    for n in TEST:
        x, y, _ = records[n]
        nearest = min(ESTIMATION, key=lambda m: abs(amplitude[m] - amplitude[n]))
        errors = {}
        for name, run in (
            ("pooled", simulate_vector(pooled, amplitude[n], x, y)),
            ("separate", simulate_vector(separate[nearest], 0.0, x, y)),
        ):
            errors[name] = np.sqrt(np.mean((run[arguments.lags :] - y[arguments.lags :]) ** 2, axis=0))
        print(
            f"{n:5d}  {amplitude[n]:7.1f} N   "
            + " ".join(f"{e:.4f}" for e in errors["pooled"])
            + f"          (level {nearest}) "
            + " ".join(f"{e:.4f}" for e in errors["separate"])
        )
    print(f"\nModes of the pooled model ({BAND[0]:g}–{BAND[1]:g} Hz, ζ < {MAX_DAMPING:g}): f [Hz] (ζ [%])")
    table = {}
    for n in range(1, 8):
        frequencies, damping = modal_parameters(pooled, amplitude[n], fs)
        keep = (frequencies > BAND[0]) & (frequencies < BAND[1]) & (damping > 0) & (damping < MAX_DAMPING)
        table[n] = (frequencies[keep], damping[keep])
        listed = ", ".join(f"{f:.2f} ({100 * z:.2f})" for f, z in zip(*table[n], strict=True))
        where = "estimation" if n in ESTIMATION else "test" if n in TEST else "outside the estimation range"
        print(f"level {n} ({amplitude[n]:5.1f} N, {where}): {listed}")
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    first = [table[n][0][0] if table[n][0].size else np.nan for n in range(1, 8)]
    first_damping = [100 * table[n][1][0] if table[n][1].size else np.nan for n in range(1, 8)]
    levels = [amplitude[n] for n in range(1, 8)]
    top.plot(levels, first, "o-", color="#1f77b4")
    bottom.plot(levels, first_damping, "o-", color="#e4572e")
    for axis in (top, bottom):
        for n in ESTIMATION:
            axis.axvline(amplitude[n], color="#999", lw=0.8, ls=":")
        axis.grid(alpha=0.3)
    top.set_ylabel("natural frequency [Hz]")
    bottom.set_ylabel("damping ratio ζ [%]")
    bottom.set_xlabel("excitation level: force standard deviation [N] (dotted: estimation levels 3, 5, 7)")
    top.set_title("F-16 GVT, lowest mode of the pooled vector model against excitation level")
    figure.tight_layout()
    arguments.plot.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(arguments.plot, dpi=120)
    print(f"\nplot: {arguments.plot}")


if __name__ == "__main__":
    main()
