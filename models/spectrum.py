"""The residual spectrum (Welch) and the frequencies where it has a significant peak."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage, signal, special

from models.errors import InputError
from models.series import checked_series, sidak


@dataclass(frozen=True)
class SpectralPeak:
    """A significant residual-spectrum peak: frequency [Hz], PSD [unit²/Hz], PSD / background."""

    frequency: float
    power: float
    ratio: float


@dataclass(frozen=True, eq=False)
class ResidualSpectrum:
    """Welch PSD of a residual, its smooth background and the peaks significantly above it.

    ``frequencies`` in Hz, ``psd`` and ``background`` in unit²/Hz. A bin is significant when
    psd/background > ``threshold``; ``dof`` and ``background_dof`` are the equivalent χ² degrees
    of freedom of one Welch estimate and of the background, ``bins_tested`` the number of bins
    the Šidák correction covers (all but DC and Nyquist). Passes when there is no peak.
    """

    frequencies: np.ndarray
    psd: np.ndarray
    background: np.ndarray
    peaks: tuple[SpectralPeak, ...]
    threshold: float
    dof: float
    background_dof: float
    segments: int
    bins_tested: int
    alpha: float

    @property
    def passed(self) -> bool:
        return not self.peaks

    def as_dict(self) -> dict[str, Any]:
        """JSON-serialisable figures, the spectrum and its background included."""
        return {
            "alpha": self.alpha,
            "passed": self.passed,
            "threshold": self.threshold,
            "dof": self.dof,
            "background_dof": self.background_dof,
            "segments": self.segments,
            "bins_tested": self.bins_tested,
            "peaks": [asdict(peak) for peak in self.peaks],
            "frequencies": self.frequencies.tolist(),
            "psd": self.psd.tolist(),
            "background": self.background.tolist(),
        }


def welch_dof(window: np.ndarray, step: int, segments: int) -> float:
    """Equivalent degrees of freedom of a Welch estimate (Percival & Walden 1993, eq. 292b).

    ν = 2K / (1 + 2·Σ_{m=1}^{K−1} (1 − m/K)·|Σ_t h(t)h(t + m·step)|²), with the window h
    normalised to Σh² = 1 and K segments: 2K without overlap, about 1.9K for a Hann window at
    50 % overlap.
    """
    h = window / np.sqrt(np.sum(window**2))
    overlap = sum(
        (1.0 - m / segments) * float(np.dot(h[m * step :], h[: h.size - m * step])) ** 2
        for m in range(1, segments)
        if m * step < h.size
    )
    return 2.0 * segments / (1.0 + 2.0 * overlap)


MIN_SEGMENT = 16


def residual_spectrum(
    e: ArrayLike,
    fs: float,
    alpha: float = 0.05,
    nperseg: int | None = None,
    smoothing_bins: int = 31,
) -> ResidualSpectrum:
    """Welch PSD of the residual and the frequencies where it has a significant peak.

    **Estimate.** ``scipy.signal.welch``: Hann window, 50 % overlap, mean removed, one-sided
    density in unit²/Hz, ``nperseg`` = min(256, N // 4) by default (bin width fs/nperseg).
    Where the true spectrum is locally flat, each estimate is background·χ²_ν/ν with ν the
    equivalent degrees of freedom (:func:`welch_dof`; ≈ 2K for K segments without overlap).

    **Background.** The running median over ``smoothing_bins`` bins (w), divided by the median
    of χ²_ν/ν so that it estimates the local mean level. The median of w normal samples has
    π/2 times the variance of their mean (Kendall & Stuart), and Welch bins j apart are
    correlated by ρ_j = |Σ h²·e^{−2πij·n/nperseg}| / Σ h² (4/9 and 1/36 squared for Hann), so the
    background behaves as a χ² estimate with ν_B = (2/π)·ν·w / (1 + 2·Σ_j ρ_j²) degrees of freedom.

    **Test.** psd/background is then approximately F(ν, ν_B); a bin is significant when it
    exceeds the F quantile at 1 − α_M, α_M = 1 − (1 − α)^{1/M} for the M bins tested (DC and
    Nyquist, with ν/2 degrees of freedom, are not). Adjacent bins are correlated, so the
    Šidák correction is conservative: a white residual shows a peak in 2–3 % of records at
    α = 0.05 (measured, N = 700–8000; 6 % with a χ²_ν threshold that ignores the background's
    own error). Each run of adjacent significant bins is one peak, reported at its highest
    bin. A weak periodic disturbance (mains hum, an unmeasured rotating force) that the
    correlation tests miss shows here as a narrow peak.
    """
    (e,) = checked_series(1, alpha, e=e)
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"fs must be a positive sampling frequency in Hz, got {fs}")
    n = e.size
    if n < 4 * MIN_SEGMENT:
        raise InputError(
            f"{n} samples is too short for a residual spectrum; it needs at least {4 * MIN_SEGMENT}"
        )
    nperseg = min(256, n // 4) if nperseg is None else nperseg
    if isinstance(nperseg, bool) or not isinstance(nperseg, int | np.integer) or nperseg < MIN_SEGMENT:
        raise InputError(f"nperseg must be a whole number of at least {MIN_SEGMENT}, got {nperseg!r}")
    if n < 2 * nperseg:
        raise InputError(
            f"{n} samples is too short for nperseg = {nperseg}: Welch averaging needs at least "
            f"2·nperseg = {2 * nperseg} samples"
        )
    bins_tested = nperseg // 2 - 1
    if isinstance(smoothing_bins, bool) or not isinstance(smoothing_bins, int | np.integer):
        raise InputError(f"smoothing_bins must be a whole number, got {smoothing_bins!r}")
    if smoothing_bins < 3 or smoothing_bins % 2 == 0 or smoothing_bins > bins_tested:
        raise InputError(
            f"smoothing_bins must be odd, at least 3 and at most the {bins_tested} bins tested, "
            f"got {smoothing_bins}"
        )
    window = signal.get_window("hann", nperseg)
    step = nperseg - nperseg // 2
    segments = 1 + (n - nperseg) // step
    frequencies, psd = signal.welch(e, fs=fs, window=window, noverlap=nperseg // 2)
    dof = welch_dof(window, step, segments)
    bin_correlation = np.abs(np.fft.rfft(window**2))[1:] / np.sum(window**2)
    background_dof = 2.0 / np.pi * dof * smoothing_bins / (1.0 + 2.0 * float(np.sum(bin_correlation**2)))
    inner = slice(1, psd.size - 1)
    background = np.empty_like(psd)
    background[inner] = ndimage.median_filter(psd[inner], size=smoothing_bins, mode="reflect") / (
        float(special.chdtri(dof, 0.5)) / dof
    )
    background[0], background[-1] = background[1], background[-2]
    threshold = float(special.fdtri(dof, background_dof, 1.0 - sidak(alpha, bins_tested)))
    ratio = psd / background
    significant = np.zeros(psd.size, dtype=np.int8)
    significant[inner] = ratio[inner] > threshold
    edges = np.flatnonzero(np.diff(np.concatenate(([0], significant, [0]))))
    peaks = []
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        top = start + int(np.argmax(psd[start:stop]))
        peaks.append(SpectralPeak(float(frequencies[top]), float(psd[top]), float(ratio[top])))
    return ResidualSpectrum(
        frequencies=frequencies,
        psd=psd,
        background=background,
        peaks=tuple(peaks),
        threshold=threshold,
        dof=dof,
        background_dof=background_dof,
        segments=segments,
        bins_tested=bins_tested,
        alpha=float(alpha),
    )
