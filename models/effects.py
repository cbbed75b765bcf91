"""Candidate effects: the named physical effects a NARX model may lack, as families of regressors.

Each family is sized to the model it would extend. The lags span those of the model (at least
1 … 4 for y): an effect entering the physics on an unmeasured mass reaches the measured
response through the same dynamics, at those lags. Velocities enter as first differences of
the response, dy[t-k] = y[t-k] − y[t-k-1].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import optimize

from models.errors import InputError
from models.spectrum import excited_intervals, residual_spectrum
from models.terms import WAVES, Factor, Term, regressor_matrix

EffectKind = Literal["terms", "output_shift", "periodic", "noise"]


@dataclass(frozen=True)
class Effect:
    """A named effect and the regressors that represent it.

    ``kind`` says how the effect is tested against a residual:

    - "terms": its terms' regressors, entering one by one while significant;
    - "output_shift": one regressor, the direction in which an offset of the measured output
      moves the model's prediction (:func:`offset_direction`); adding it adds ``terms``, the
      monomials that offset brings into the model;
    - "periodic": a sine and a cosine at each significant peak of the residual spectrum that
      the input does not excite (:func:`periodic_terms`); its ``terms`` are found from the
      residual, so empty here;
    - "noise": moving-average terms e[t-k] of the residual itself, which make the model a
      NARMAX estimated by extended least squares (:mod:`models.narmax`); no terms either.
    """

    name: str
    description: str
    terms: tuple[Term, ...]
    kind: EffectKind = "terms"


def linear_terms(ny: int, nx: int, delay: int = 1) -> tuple[Term, ...]:
    """A linear ARX structure: y[t-1] … y[t-ny] and x[t-delay] … x[t-delay-nx+1]."""
    if ny < 1 or nx < 1 or delay < 0:
        raise InputError(
            f"a linear ARX structure needs ny >= 1, nx >= 1, delay >= 0; got {ny}, {nx}, {delay}"
        )
    ys = [Term((Factor("y", lag),)) for lag in range(1, ny + 1)]
    xs = [Term((Factor("x", lag),)) for lag in range(delay, delay + nx)]
    return tuple(ys + xs)


def candidate_effects(terms: Sequence[Term]) -> list[Effect]:
    """The effect families a model with these terms may lack; terms it has are left out."""
    y_lags = [f.lag for t in terms for f in t.factors if f.signal == "y"]
    x_lags = sorted({f.lag for t in terms for f in t.factors if f.signal == "x"}) or [1]
    ny = max(y_lags, default=0)
    lags_y = range(1, max(ny, 4) + 1)

    def powers(signal: str, lags: Sequence[int], power: int) -> tuple[Term, ...]:
        return tuple(Term((Factor(signal, lag, power),)) for lag in lags)

    shorter_delay = [x_lags[0] - 1] if x_lags[0] > 0 else []
    velocity = [Factor("dy", lag) for lag in lags_y]
    effects = [
        Effect("cubic_stiffness", "cubic restoring force: a stiffening spring", powers("y", lags_y, 3)),
        Effect(
            "quadratic_stiffness", "quadratic restoring force: an asymmetric spring", powers("y", lags_y, 2)
        ),
        Effect(
            "coulomb_friction",
            "dry friction: a force of constant size against the velocity, sign(dy)",
            tuple(Term((Factor("dy", v.lag, function="sign"),)) for v in velocity),
        ),
        Effect(
            "quadratic_damping",
            "quadratic damping: a force growing with the velocity squared, dy·|dy|",
            tuple(Term.of([v, Factor("dy", v.lag, function="abs")]) for v in velocity),
        ),
        Effect(
            "cubic_damping",
            "cubic damping: a force growing with the velocity cubed, dy³",
            tuple(Term((Factor("dy", v.lag, 3),)) for v in velocity),
        ),
        Effect(
            "input_nonlinearity",
            "nonlinear excitation path: actuator or amplifier, x² and x³",
            powers("x", x_lags, 2) + powers("x", x_lags, 3),
        ),
        Effect(
            "missing_lags",
            "dynamics beyond the declared lags, or a shorter input delay",
            powers("y", [ny + 1, ny + 2], 1) + powers("x", [x_lags[-1] + 1, *shorter_delay], 1),
        ),
        Effect("offset", "constant offset: sensor bias or static load", offset_terms(terms), "output_shift"),
        Effect(
            "periodic_disturbance",
            "a periodic force or interference at a residual spectral peak",
            (),
            "periodic",
        ),
        Effect("moving_average_noise", "coloured noise: moving-average terms e[t-k] (NARMAX)", (), "noise"),
    ]
    return unused(effects, terms)


def unused(effects: Sequence[Effect], terms: Sequence[Term]) -> list[Effect]:
    """The effects with the terms the model already has left out; those with none left dropped
    (periodic and noise effects, whose regressors come from the residual, always stay)."""
    present = set(terms)
    kept = []
    for effect in effects:
        new = tuple(t for t in effect.terms if t not in present)
        if new or effect.kind in ("periodic", "noise"):
            kept.append(Effect(effect.name, effect.description, new, effect.kind))
    return kept


def offset_terms(terms: Sequence[Term]) -> tuple[Term, ...]:
    """The constant and every monomial an offset c of y adds to the model to first order in c:
    each y factor of power p contributes the term with that factor's power lowered by one."""
    lowered = [Term()]
    for term in terms:
        for index in _y_factors(term):
            lowered.append(_lower(term, index))
    return tuple(dict.fromkeys(lowered))


def offset_direction(
    terms: Sequence[Term], theta: np.ndarray, x: np.ndarray, y: np.ndarray, lag: int
) -> np.ndarray:
    """∂ŷ/∂c for a model ŷ[t] = c + F(y − c, x) at c = 0, rows t = lag … N−1:

        g[t] = 1 − Σ_j θ_j Σ_{y factors f of term j} p_f · φ_j^(f↓)[t],

    where φ_j^(f↓) is term j with the power p_f of factor f lowered by one. A sensor offset c
    adds c·g to the one-step prediction, so g is the one regressor that tests for it.
    """
    lowered: list[Term] = []
    weights: list[float] = []
    for term, coefficient in zip(terms, theta, strict=True):
        for index in _y_factors(term):
            lowered.append(_lower(term, index))
            weights.append(coefficient * term.factors[index].power)
    direction = np.ones(len(y) - lag)
    if lowered:
        columns, _ = regressor_matrix(lowered, x, y, lag)
        direction -= columns @ np.asarray(weights)
    return direction


def _y_factors(term: Term) -> list[int]:
    return [i for i, factor in enumerate(term.factors) if factor.signal == "y"]


def _lower(term: Term, index: int) -> Term:
    factor = term.factors[index]
    rest = [f for i, f in enumerate(term.factors) if i != index]
    if factor.power > 1:
        rest.append(Factor(factor.signal, factor.lag, factor.power - 1))
    return Term.of(rest)


def periodic_terms(residual: np.ndarray, alpha: float, x: np.ndarray) -> tuple[Term, ...]:
    """A sine and a cosine at each significant peak of the residual's spectrum that the input
    ``x`` does not excite.

    Peaks come from :func:`models.spectrum.residual_spectrum` at level ``alpha``; Welch's bins
    are far too coarse for a regressor that must stay in phase over the whole record, so each
    frequency is then refined to the maximum of the periodogram |Σ e[t]·exp(−2πi·f·t)|² near
    the peak: on an 8× zero-padded FFT grid, then by a bounded scalar search within one grid step.
    A peak whose frequency lies on one of the input's lines, or on their harmonics and
    intermodulation products (:func:`models.spectrum.excited_intervals`), is the periodic
    residual a wrong model leaves under a periodic input, not an external tone: it is left out.
    """
    spectrum = residual_spectrum(residual, 1.0, alpha)
    if not spectrum.peaks:
        return ()
    excited = excited_intervals(x, 1.0, alpha)
    n = residual.size
    padded = 8 * n
    power = np.abs(np.fft.rfft(residual - residual.mean(), padded)) ** 2
    grid = np.fft.rfftfreq(padded)
    times = np.arange(n, dtype=np.float64)
    half_bin = 0.5 / (spectrum.frequencies.size - 1)  # half a Welch bin, in cycles per sample

    def periodogram(f: float) -> float:
        return -(abs(np.dot(residual, np.exp(-2j * np.pi * f * times))) ** 2)

    terms: list[Term] = []
    for peak in spectrum.peaks:
        near = np.flatnonzero(np.abs(grid - peak.frequency) <= half_bin)
        coarse = grid[near[np.argmax(power[near])]]
        step = 1.0 / padded
        low, high = max(coarse - step, 1e-9), min(coarse + step, 0.5 - 1e-9)
        frequency = float(optimize.minimize_scalar(periodogram, bounds=(low, high), method="bounded").x)
        if np.any((excited[:, 0] <= frequency) & (frequency <= excited[:, 1])):
            continue
        # Rounded so that the term's name stays short; the phase error this leaves over 10⁶
        # samples is below 10⁻³ of a cycle.
        frequency = float(f"{frequency:.10g}")
        terms += [Term((Factor(wave, 0, frequency=frequency),)) for wave in WAVES]
    return tuple(dict.fromkeys(terms))
