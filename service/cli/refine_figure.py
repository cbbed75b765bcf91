"""The refinement report as a PNG: residual whiteness and spectrum before and after, and the free run."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from models.explanation import Explanation
from models.refinement import RefinementReport

SHOWN = 800  # samples of the free run shown: the end of the test, where errors have had time to grow
# The effects' colours: none of the declared (C3) and refined (C0) models'.
EFFECT_COLOURS = ("C2", "C4", "C1", "C5", "C6", "C8", "C9", "C7")


def write_refinement_figure(
    report: RefinementReport,
    x: np.ndarray,
    y: np.ndarray,
    initial: int,
    fs: float | None,
    path: Path,
    output: str = "y",
    unit: str | None = None,
    explanation: Explanation | None = None,
) -> Path:
    """:func:`draw_refinement_figure` as a PNG at ``path``."""
    figure = draw_refinement_figure(report, x, y, initial, fs, output, unit, explanation)
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
    explanation: Explanation | None = None,
) -> Figure:
    """Three panels on the held-out data (x, y), whose first ``initial`` samples start the models:
    the residual autocorrelation with its band, the residual spectrum with its background and
    significant peaks, and the measured output (named ``output``, in ``unit`` where stated)
    against both models' free runs. Frequencies are in Hz and the free run over time where the
    sampling rate ``fs`` [Hz] is known (the rate the report's spectra were computed at), in
    cycles per sample and over samples where it is not. With the refined model's
    ``explanation`` on (x, y) and effects added, a fourth panel: each effect's contribution to
    each step over the same stretch (:mod:`models.explanation`)."""
    # Names and units are the user's text, not mathtext: a '$' pair would be parsed, and fail.
    output, unit = output.replace("$", r"\$"), unit and unit.replace("$", r"\$")
    explained = explanation is not None and bool(explanation.effects)
    mosaic = [["correlation"] * 2, ["spectrum"] * 2, ["run"] * 2] + (
        [["steps", "shares"]] if explained else []
    )
    figure, panels = plt.subplot_mosaic(
        mosaic, figsize=(9, 3.3 * len(mosaic)), width_ratios=(2, 1), constrained_layout=True
    )
    correlation, spectrum, run = (panels[name] for name in ("correlation", "spectrum", "run"))
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
    in_unit = f" [{unit}]" if unit else " (unit not stated: --unit)"
    run.set(
        xlabel="time [s]" if fs else "sample",
        ylabel=f"{output}{in_unit}",
        title="Measured and simulated output (end of the test data)",
    )
    for axes in (correlation, spectrum, run):
        axes.legend(fontsize=8)
    if explanation is not None and explained:
        names = [effect.name for effect in report.refinement.effects_added]
        _draw_steps(panels["steps"], names, explanation, shown, fs, output, in_unit)
        _draw_shares(panels["shares"], names, explanation, unit)
    return figure


def _draw_steps(
    axes: Axes,
    names: list[str],
    explanation: Explanation,
    shown: slice,
    fs: float | None,
    output: str,
    in_unit: str,
) -> None:
    """Each effect's contribution to each step of the refined model's run over the ``shown``
    samples: its terms times their coefficients."""
    for number, (name, contribution) in enumerate(zip(names, explanation.effects, strict=True)):
        if not contribution.series.size:  # no terms of its own: moving-average noise, saturation
            continue
        samples = explanation.first + np.arange(contribution.series.size)
        kept = samples >= shown.start
        colour = EFFECT_COLOURS[number % len(EFFECT_COLOURS)]
        axes.plot(samples[kept] / (fs or 1.0), contribution.series[kept], color=colour, lw=0.8, label=name)
    axes.axhline(0.0, color="k", lw=0.5)
    axes.set(
        xlabel="time [s]" if fs else "sample",
        ylabel=f"added to each step of {output}{in_unit}",
        title=f"Each effect's terms × coefficients\nalong the refined model's {explanation.along}",
    )
    axes.legend(fontsize=8)


def _draw_shares(axes: Axes, names: list[str], explanation: Explanation, unit: str | None) -> None:
    """Each effect's two shares of the output's RMS as horizontal bars on a log scale: of each
    step, and how far the free run moves without it (hatched to the edge where it diverges).
    Those with neither (moving-average noise, which the free run does not hold) are named
    beneath."""
    drawn, left_out = [], []
    for name, contribution in zip(names, explanation.effects, strict=True):
        if contribution.share is None and contribution.removal is None:
            left_out.append(name)
        else:
            drawn.append((name, contribution))
    rows = np.arange(len(drawn))[::-1]  # the first effect on top
    bars = (
        ("of each step", "0.6", 0.2, [c.share for _, c in drawn]),
        ("the free run's move without it", "C0", -0.2, [c.removal for _, c in drawn]),
    )
    finite = [v for *_, values in bars for v in values if v is not None and 0 < v < np.inf]
    low, high = (min(finite) / 3, max(max(finite) * 3, 1.5)) if finite else (1e-6, 1.5)
    for _, colour, offset, values in bars:
        for row, value in zip(rows, values, strict=True):
            if value is None:  # moving-average noise: not in the free run
                continue
            diverges = not np.isfinite(value)
            width = high if diverges else max(value, low)
            axes.barh(row + offset, width, height=0.38, color=colour, hatch="//" if diverges else None)
            axes.annotate(
                "diverges" if diverges else f"{100 * value:.3g} %",
                (low if diverges else width, row + offset),
                xytext=(3, 0),
                textcoords="offset points",
                va="center",
                fontsize=7,
                color="w" if diverges else "k",
            )
    axes.set_xscale("log")
    axes.set(
        xlim=(low, high),
        yticks=rows,
        yticklabels=[name for name, _ in drawn],
        xlabel="share of the output's RMS",
        title=f"Shares of the output's RMS\n({explanation.output_rms:.3g}{f' {unit}' if unit else ''})",
    )
    handles = [Patch(color=colour, label=label) for label, colour, *_ in bars]
    if left_out:
        handles.append(Patch(color="none", label=f"not drawn: {', '.join(dict.fromkeys(left_out))}"))
    axes.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(0.0, -0.22))
