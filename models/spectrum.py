"""The residual spectrum (Welch) and the frequencies where it has a significant peak."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import scipy
from numpy.typing import ArrayLike
from scipy import special

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

    def to_dict(self) -> dict[str, Any]:
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
    nperseg = _segment_length(e.size, fs, nperseg, smoothing_bins)
    bins_tested = nperseg // 2 - 1
    window = scipy.signal.get_window("hann", nperseg)
    step = nperseg - nperseg // 2
    segments = 1 + (e.size - nperseg) // step
    frequencies, psd = scipy.signal.welch(e, fs=fs, window=window, noverlap=nperseg // 2)
    dof = welch_dof(window, step, segments)
    bin_correlation = np.abs(np.fft.rfft(window**2))[1:] / np.sum(window**2)
    background_dof = 2.0 / np.pi * dof * smoothing_bins / (1.0 + 2.0 * float(np.sum(bin_correlation**2)))
    background = _background(psd, dof, smoothing_bins)
    threshold = float(special.fdtri(dof, background_dof, 1.0 - sidak(alpha, bins_tested)))
    ratio = psd / background
    return ResidualSpectrum(
        frequencies=frequencies,
        psd=psd,
        background=background,
        peaks=_peaks(frequencies, psd, ratio, threshold),
        threshold=threshold,
        dof=dof,
        background_dof=background_dof,
        segments=segments,
        bins_tested=bins_tested,
        alpha=float(alpha),
    )


def _segment_length(n: int, fs: float, nperseg: int | None, smoothing_bins: int) -> int:
    """The Welch segments' length (by default min(256, N // 4)), refused, with the rate and the
    smoothing, where a record of ``n`` samples cannot carry the test."""
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"fs must be a positive sampling frequency in Hz, got {fs}")
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
    return nperseg


def _background(psd: np.ndarray, dof: float, smoothing_bins: int) -> np.ndarray:
    """The local mean level of each bin: the running median over ``smoothing_bins`` bins over
    the median of χ²_ν/ν; DC and Nyquist take their neighbour's."""
    inner = slice(1, psd.size - 1)
    background = np.empty_like(psd)
    background[inner] = scipy.ndimage.median_filter(psd[inner], size=smoothing_bins, mode="reflect") / (
        float(special.chdtri(dof, 0.5)) / dof
    )
    background[0], background[-1] = background[1], background[-2]
    return background


def _peaks(
    frequencies: np.ndarray, psd: np.ndarray, ratio: np.ndarray, threshold: float
) -> tuple[SpectralPeak, ...]:
    """Each run of adjacent significant bins (DC and Nyquist not tested) as one peak, at its
    strongest bin."""
    significant = np.zeros(psd.size, dtype=np.int8)
    significant[1 : psd.size - 1] = ratio[1 : psd.size - 1] > threshold
    edges = np.flatnonzero(np.diff(np.concatenate(([0], significant, [0]))))
    peaks = []
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        top = start + int(np.argmax(psd[start:stop]))
        peaks.append(SpectralPeak(float(frequencies[top]), float(psd[top]), float(ratio[top])))
    return tuple(peaks)


PRODUCT_ORDER = 3  # harmonics and intermodulation products up to this order
LINE_SMOOTHING = 31  # bins over which a line's background is taken
LINE_QUANTILE = 0.25  # the quantile of those bins that estimates it
# The background is taken no lower than this share of the strongest bin (−120 dB): below any
# acquisition's dynamic range, far above float64 rounding, whose bins a noiseless input would
# otherwise show as lines.
DYNAMIC_RANGE = 1e-12
EXCITATION_SHARE = 0.99  # share of the narrowband power held by the bins whose products are formed
NARROWBAND_SHARE = 0.9  # share of a segment's power held by its strongest Welch bin and two either side


def excited_intervals(x: ArrayLike, fs: float = 1.0, alpha: float = 0.01) -> np.ndarray:
    """The frequency intervals [Hz] where the input excites the system narrowband, with their
    harmonics and intermodulation products: rows (low, high), ascending, within 0 … fs/2.

    A model that lacks dynamics or a nonlinearity, driven by a periodic input, leaves a periodic
    residual: its spectral peaks sit on the input's lines and on their products, and a sine of
    absolute time fits them as well as it would an external tone. What tells an external tone
    apart is a residual peak where the input has no narrowband excitation:

    - **a multisine, a sine, any periodic input**: its lines, the bins of the N-point
      periodogram that are local maxima above the local background by more than the
      F(2, ν_B) quantile at the Šidák level for the N/2 bins. The background is the running
      25th percentile of ``LINE_SMOOTHING`` bins divided by −ln 0.75 (so that it estimates the
      local mean of an exponentially distributed periodogram): a low quantile, because a
      multisine excites every second bin of a record two periods long. With a rectangular
      window the lines of a record of whole periods fall exactly on bins, with nothing
      between; a Hann window, whose leakage falls off fast, finds lines off the bin grid (a
      record cut within a period) that the rectangular window's leakage hides, and adds
      those more than one bin from any line found already.
    - **a sweep, a stepped sine**: narrowband at every moment, so every frequency it passes
      is excited. When most Welch segments (Hann, ``nperseg`` = min(256, N // 4)) hold at least
      ``NARROWBAND_SHARE`` of their power within two bins of their strongest bin, and that bin
      moves, the band it spans, one Welch bin wider each side, is excited.
    - **random (broadband) input**: every frequency is excited, but none narrowband: a
      residual peak then needs a cause the input does not have, and no interval is returned.

    The excitation is the strongest of those lines and band bins, holding ``EXCITATION_SHARE``
    of their power; the weaker lines (the structure's own distortion fed back into a measured
    force, mains pickup) are excited themselves, but a product of one of them is weaker than
    the excitation's own by its amplitude ratio. The excitation's products of order 2 and 3
    (sums and differences f₁ ± f₂ ± f₃, harmonics among them) are the support of its
    convolutions with itself. When its L bins have a common divisor g > 1 — a periodic input
    whose record holds g periods, or a multisine exciting every g-th line of its grid — every
    nonlinearity, of any order, responds on the multiples of g alone, and all of them are
    excited; provided that L lines sharing the divisor by chance, with probability g^−(L−1),
    is less likely than α (two lines at even bins do not make a period).

    Each bin stands for the frequencies within half a bin of it: an N-sample record does not
    tell apart two frequencies closer than 1/N (Rayleigh). In a record of whole periods, lines
    and products are exact, and a tone half a bin or more from every one of them is told apart.
    A record cut within a period has its lines off the bin grid: each is placed at its nearest
    bin, its products up to 1.5 bins from where they are placed, and the common divisor is lost.
    """
    (x,) = checked_series(1, alpha, x=x)
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"fs must be a positive sampling frequency in Hz, got {fs}")
    n = x.size
    if n < 4 * MIN_SEGMENT:
        raise InputError(f"{n} samples is too short to read the input's spectrum; it needs {4 * MIN_SEGMENT}")
    x = x - x.mean()
    narrowband = _lines(x, alpha)
    band = _swept_band(x)
    if band is not None:
        narrowband[band[0] : band[1] + 1] = True
    if not narrowband.any():
        return np.empty((0, 2))
    power = np.abs(np.fft.rfft(x)) ** 2
    ranked = np.flatnonzero(narrowband)[np.argsort(power[narrowband])[::-1]]
    share = np.cumsum(power[ranked]) / np.sum(power[ranked])
    excitation = np.zeros_like(narrowband)
    excitation[ranked[: np.searchsorted(share, EXCITATION_SHARE) + 1]] = True
    excited = _products(excitation) | narrowband
    bins = np.flatnonzero(excitation)
    divisor = int(np.gcd.reduce(bins))
    if divisor > 1 and (bins.size - 1) * np.log(divisor) >= -np.log(alpha):
        excited[::divisor] = True
    edges = np.flatnonzero(np.diff(np.concatenate(([0], excited.view(np.int8), [0]))))
    limits = np.column_stack([edges[::2] - 0.5, edges[1::2] - 0.5])  # in bins
    return np.clip(limits * fs / n, 0.0, fs / 2)


def _lines(x: np.ndarray, alpha: float) -> np.ndarray:
    """The input's lines, True at their periodogram bins (see :func:`excited_intervals`)."""
    n = x.size
    # The p-quantile q = −ln(1 − p) of an exponential variable of mean 1 has the sample
    # quantile's variance p / (w·(1 − p)) over w bins: as a χ²_ν/ν estimate of the mean it has
    # ν = 2·w·(1 − p)·q² / p degrees of freedom, fewer for a Hann window's correlated bins.
    q = -np.log1p(-LINE_QUANTILE)
    dof = 2.0 * LINE_SMOOTHING * (1.0 - LINE_QUANTILE) * q**2 / LINE_QUANTILE
    lines = np.zeros(n // 2 + 1, dtype=bool)
    for window in (np.ones(n), scipy.signal.get_window("hann", n)):
        power = np.abs(np.fft.rfft(x * window)) ** 2
        inner = power[1:-1]
        background = scipy.ndimage.percentile_filter(
            inner, 100 * LINE_QUANTILE, size=LINE_SMOOTHING, mode="reflect"
        )
        background = np.maximum(background, DYNAMIC_RANGE * power.max())
        correlation = np.abs(np.fft.rfft(window**2))[1:] / np.sum(window**2)
        background_dof = dof / (1.0 + 2.0 * float(np.sum(correlation**2)))
        threshold = float(special.fdtri(2.0, background_dof, 1.0 - sidak(alpha, inner.size)))
        peaks = np.zeros_like(lines)
        peaks[1:-1] = (inner >= power[:-2]) & (inner >= power[2:]) & (inner * q > threshold * background)
        lines |= peaks & ~scipy.ndimage.binary_dilation(lines)
    return lines


def _swept_band(x: np.ndarray) -> tuple[int, int] | None:
    """The band a sweep passes through, as a range of periodogram bins; None when the input is
    not narrowband most of the time, or its narrowband peak stays put (a line, found as such)."""
    n = x.size
    nperseg = min(256, n // 4)
    _, _, power = scipy.signal.spectrogram(x, window="hann", nperseg=nperseg, noverlap=nperseg // 2)
    strongest = np.argmax(power, axis=0)
    around = np.pad(power, ((2, 2), (0, 0)))
    columns = np.arange(power.shape[1])
    near = sum(around[strongest + 2 + d, columns] for d in range(-2, 3))
    narrowband = near > NARROWBAND_SHARE * power.sum(axis=0)
    if 2 * np.count_nonzero(narrowband) < narrowband.size:
        return None
    low, high = int(strongest[narrowband].min()), int(strongest[narrowband].max())
    if high - low <= 1:
        return None
    scale = n / nperseg  # periodogram bins per Welch bin
    return max(int((low - 1) * scale), 0), min(int(np.ceil((high + 1) * scale)), n // 2)


def _products(excited: np.ndarray) -> np.ndarray:
    """The bins (0 … Nyquist) of the excited set and of the sums and differences of up to
    ``PRODUCT_ORDER`` of its frequencies: the support of the two-sided set's convolutions."""
    two_sided = np.concatenate((excited[:0:-1], excited)).astype(np.float64)  # bins −N/2 … N/2
    products = excited.copy()
    convolved = two_sided
    for _ in range(PRODUCT_ORDER - 1):
        convolved = (scipy.signal.fftconvolve(convolved, two_sided) > 0.5).astype(np.float64)
        centre = convolved.size // 2
        products |= convolved[centre : centre + excited.size] > 0.5
    return products
