"""The refinement report as a PNG: residual whiteness and spectrum before and after, and the free run."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from models.refinement import RefinementReport

SHOWN = 800  # samples of the free run shown: the end of the test, where errors have had time to grow


def write_refinement_figure(
    report: RefinementReport,
    x: np.ndarray,
    y: np.ndarray,
    initial: int,
    fs: float | None,
    path: Path,
    output: str = "y",
    unit: str | None = None,
) -> Path:
    """:func:`draw_refinement_figure` as a PNG at ``path``."""
    figure = draw_refinement_figure(report, x, y, initial, fs, output, unit)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def draw_refinement_figure(
    report: RefinementReport,
    x: np.ndarray,
    y: np.ndarray,
    initial: int,
    fs: float | None,
    output: str = "y",
    unit: str | None = None,
) -> Figure:
    """Three panels on the held-out data (x, y), whose first ``initial`` samples start the models:
    the residual autocorrelation with its band, the residual spectrum with its background and
    significant peaks, and the measured output (named ``output``, in ``unit`` where stated)
    against both models' free runs. Frequencies are in Hz and the free run over time where the
    sampling rate ``fs`` [Hz] is known (the rate the report's spectra were computed at), in
    cycles per sample and over samples where it is not."""
    # Names and units are the user's text, not mathtext: a '$' pair would be parsed, and fail.
    output, unit = output.replace("$", r"\$"), unit and unit.replace("$", r"\$")
    figure, (correlation, spectrum, run) = plt.subplots(3, 1, figsize=(9, 10), constrained_layout=True)
    shown = slice(max(initial, len(y) - SHOWN), len(y))
    samples = np.arange(shown.start, shown.stop) / (fs or 1.0)
    run.plot(samples, y[shown], color="k", lw=1.6, label="measured")
    models = (("declared", report.refinement.declared, report.before, "C3"),
              ("refined", report.refinement.refined, report.after, "C0"))  # fmt: skip
    for label, model, assessment, colour in models:
        start = max(initial - model.max_lag, 0)
        simulated = model.simulate(x[start:], y[start:])
        run.plot(samples, simulated[shown.start - start :], color=colour, lw=0.8, label=f"{label} (free run)")
        diagnostics = assessment.diagnostics
        if diagnostics is None:  # a test part too short for the residual tests
            continue
        ee = diagnostics.billings_voon.ee
        correlation.plot(ee.lags, ee.values, "o-", color=colour, ms=3, lw=0.8, label=label)
        correlation.fill_between(ee.lags, -ee.band, ee.band, color=colour, alpha=0.12)
        band = diagnostics.spectrum
        spectrum.semilogy(band.frequencies, band.psd, color=colour, lw=0.8, label=label)
        spectrum.semilogy(band.frequencies, band.background * band.threshold, color=colour, lw=0.6, ls="--")
        for peak in band.peaks:
            spectrum.annotate(f"{peak.frequency:.4g}", (peak.frequency, peak.power), color=colour, fontsize=7)
    frequency = "Hz" if fs else "cycles/sample"
    squared = f"{unit if unit.isalpha() else f'({unit})'}²/{frequency}" if unit else f"per {frequency}"
    correlation.set(
        xlabel="lag [samples]",
        ylabel="residual autocorrelation",
        title="Residual whiteness (shaded: the band that decides for all lags at once)",
    )
    spectrum.set(
        xlim=(0.0, (fs or 1.0) / 2),  # to the Nyquist frequency
        xlabel=f"frequency [{frequency}]",
        ylabel=f"residual PSD [{squared}]",
        title="Residual spectrum (Welch); dashed: significance threshold; labels: significant peaks",
    )
    run.set(
        xlabel="time [s]" if fs else "sample",
        ylabel=f"{output} [{unit}]" if unit else f"{output} (unit not stated: --unit)",
        title="Measured and simulated output (end of the test data)",
    )
    for axes in (correlation, spectrum, run):
        axes.legend(fontsize=8)
    return figure
