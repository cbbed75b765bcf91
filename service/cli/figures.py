"""PNG figures equivalent to the paper's Figures 3–6, drawn from a study result."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from models.narx import z_quantile
from recordfiles.quantities import signal_label
from simulator.paper import StudyResult
from simulator.physics import RESPONSE
from simulator.simulate import simulate
from simulator.theory import exact_trajectories

SEGMENT = slice(1000, 1300)


def write_figures(result: StudyResult, out: Path) -> list[Path]:
    paths = [
        _figure3(result, out / "figure3_prediction.png"),
        _figure4(result, out / "figure4_trajectories.png"),
        _figure5(result, out / "figure5_estimates.png"),
        _figure6(result, out / "figure6_q_statistic.png"),
    ]
    plt.close("all")
    return paths


def _figure3(result: StudyResult, path: Path) -> Path:
    """Actual vs one-step predicted response and the prediction errors (baseline model)."""
    settings = result.settings
    record = simulate(settings.scenario(), 3000, np.random.SeedSequence([settings.seed, 3]))
    model = result.baseline
    predicted = model.predict(record.x, record.y)
    actual = record.y[model.max_lag :]
    t = np.arange(len(actual))[SEGMENT] / record.fs
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    top.plot(t, actual[SEGMENT], "-", lw=1.5, label="actual")
    top.plot(t, predicted[SEGMENT], "--", lw=1.2, label="one-step predicted")
    top.set_ylabel(signal_label("y", RESPONSE))
    top.legend(loc="upper right")
    top.set_title("Figure 3 — baseline NARX: (a) response, (b) prediction error")
    bottom.plot(t, (actual - predicted)[SEGMENT], lw=0.8)
    bottom.set_ylabel(signal_label("e", RESPONSE, quantity=False))
    bottom.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _figure4(result: StudyResult, path: Path) -> Path:
    """Theoretical vs FNARX-estimated coefficient trajectories of the k2 fault mode."""
    model = result.models.k2
    k = np.linspace(model.basis.k_min, model.basis.k_max, 65)
    estimated = model.trajectories(k)
    theory = exact_trajectories(result.settings.params, "k2", k)
    fig, axes = plt.subplots(2, 4, figsize=(13, 5.5))
    for index, ax in enumerate(axes.flat):
        ax.fill_between(
            k, estimated.low[:, index], estimated.high[:, index], alpha=0.3, label="95 % interval"
        )
        ax.plot(k, estimated.values[:, index], "-", label="FNARX estimate")
        ax.plot(k, theory[:, index], "k--", lw=1, label="theoretical")
        ax.set_title(estimated.term_names[index], fontsize=10)
        ax.set_xlabel("k [%]")
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3), useOffset=True)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("Figure 4 — coefficients as functions of the fault magnitude (mode k2)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _figure5(result: StudyResult, path: Path) -> Path:
    """Point and interval estimates of k per run and case."""
    z = z_quantile(1 - result.settings.alpha)
    panels = [(c, "k2") for c in result.cases] + [(result.cases[3], "k1")]
    fig, axes = plt.subplots(1, len(panels), figsize=(16, 3.8))
    for ax, (case_result, mode) in zip(axes, panels, strict=True):
        estimates = [v.mode(mode) for v in case_result.verdicts]
        runs = np.arange(1, len(estimates) + 1)
        k_hat = np.array([m.k_hat for m in estimates])
        half = z * np.array([m.sigma_k for m in estimates])
        ax.errorbar(runs, k_hat, yerr=half, fmt="o", capsize=4, mfc="none")
        truth = case_result.case.true_k if case_result.case.fault == mode else 0.0
        ax.axhline(truth, color="k", lw=1)
        ax.set_title(f"case {case_result.case.name} under the {mode} model", fontsize=10)
        ax.set_xticks(runs)
        ax.set_xlabel("run")
    axes[0].set_ylabel("k̂ ± z·σ̂_k [%]")
    fig.suptitle("Figure 5 — fault detection: point and interval estimates (solid line: true k, or 0)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def _figure6(result: StudyResult, path: Path) -> Path:
    """Q statistic of the k2 model per run against the critical value."""
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.6))
    for ax, case_result in zip(axes, result.cases, strict=True):
        k2 = [v.mode("k2") for v in case_result.verdicts]
        runs = np.arange(1, len(k2) + 1)
        ax.bar(runs, [m.q for m in k2], color="tab:blue")
        ax.axhline(k2[0].q_critical, color="r", ls="--", label="critical point")
        ax.set_title(f"case {case_result.case.name}", fontsize=10)
        ax.set_xticks(runs)
        ax.set_xlabel("run")
        if max(m.q for m in k2) > 10 * k2[0].q_critical:
            ax.set_yscale("log")
    axes[0].set_ylabel("Q (k2 model)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Figure 6 — fault identification: Ljung–Box Q, h = {result.settings.lags}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
