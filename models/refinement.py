"""Closing the loop (SPEC §7): residual → the effect the model lacks → refined model.

Starting from a declared structure, each round

1. fits the current terms by least squares on the estimation data and takes the residual e;
2. scores every named candidate effect — a family of regressors with a physical meaning — by
   how much of e it explains. Within a family, terms enter greedily by their error reduction
   ratio against e, each after a partial F test
   F = (RSS_before − RSS_after) / (RSS_after / (N − p)) ~ F(1, N − p),
   at the Bonferroni level α / M, where M counts every candidate term of every family in the
   round: the more regressors are on offer, the stronger the evidence each must bring;
3. adds the effect that explains most, and repeats until no family has a significant term.

Candidate columns are orthogonalised against the current regressors first (e is orthogonal to
them already), so each score is the reduction of the residual sum of squares that refitting
with the new terms would achieve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg, special

from models.errors import InputError
from models.narx import NARX, fit_narx
from models.terms import Factor, Term, max_lag, parse_terms, regressor_matrix

DEFAULT_ALPHA = 0.01
MAX_ROUNDS = 10


@dataclass(frozen=True)
class Effect:
    """A named physical effect and the regressors that would represent it."""

    name: str
    description: str
    terms: tuple[Term, ...]


@dataclass(frozen=True)
class EffectScore:
    """How much of the residual an effect explains with its significant terms.

    ``explained`` is the fraction of the residual sum of squares removed; ``terms`` the
    significant ones in the order they entered, each with its partial F statistic and p-value.
    """

    name: str
    explained: float
    terms: tuple[str, ...]
    f_statistics: tuple[float, ...]
    p_values: tuple[float, ...]

    @property
    def significant(self) -> bool:
        return bool(self.terms)


@dataclass(frozen=True)
class Round:
    """One round of the loop: every effect's score, the level used, and the effect added (if any)."""

    residual_rms: float
    level: float  # the Bonferroni-corrected significance level α / M
    candidates: int  # M
    scores: tuple[EffectScore, ...]
    added: EffectScore | None


@dataclass(frozen=True)
class Refinement:
    """The declared and refined models and the rounds that led from one to the other."""

    declared: NARX
    refined: NARX
    rounds: tuple[Round, ...] = field(default=())

    @property
    def effects_added(self) -> tuple[EffectScore, ...]:
        return tuple(r.added for r in self.rounds if r.added is not None)


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
    """The effect families a model with these terms may lack, sized to its lags.

    Lags span those of the model (at least 1 … 4 for y): an effect entering the physics on an
    unmeasured mass reaches the measured response through the same dynamics, at those lags.
    """
    y_lags = [f.lag for t in terms for f in t.factors if f.signal == "y"]
    x_lags = [f.lag for t in terms for f in t.factors if f.signal == "x"]
    ny = max(y_lags, default=0)
    lags_y = range(1, max(ny, 4) + 1)
    lags_x = sorted(set(x_lags)) or [1]

    def powers(signal: str, lags: Sequence[int], power: int) -> tuple[Term, ...]:
        return tuple(Term((Factor(signal, lag, power),)) for lag in lags)

    first_x = min(lags_x)
    effects = [
        Effect(
            "cubic_stiffness",
            "a cubic restoring force (hardening or softening spring)",
            powers("y", lags_y, 3),
        ),
        Effect("quadratic_stiffness", "an asymmetric (quadratic) restoring force", powers("y", lags_y, 2)),
        Effect(
            "input_nonlinearity",
            "a nonlinear excitation path (actuator or amplifier), x² and x³",
            powers("x", lags_x, 2) + powers("x", lags_x, 3),
        ),
        Effect(
            "missing_lags",
            "dynamics beyond the declared lags, or a shorter input delay",
            powers("y", [ny + 1, ny + 2], 1)
            + powers("x", [max(lags_x) + 1] + ([first_x - 1] if first_x > 0 else []), 1),
        ),
        Effect("offset", "a constant offset (sensor bias or static load)", (Term(),)),
    ]
    present = set(terms)
    return [
        Effect(e.name, e.description, kept)
        for e in effects
        if (kept := tuple(t for t in e.terms if t not in present))
    ]


def refine(
    x: np.ndarray,
    y: np.ndarray,
    declared: Sequence[str | Term],
    effects: Sequence[Effect] | None = None,
    alpha: float = DEFAULT_ALPHA,
    max_rounds: int = MAX_ROUNDS,
) -> Refinement:
    """Refine the declared structure on estimation data (x, y) until no effect is significant."""
    if not 0 < alpha < 1:
        raise InputError(f"alpha must lie in (0, 1), got {alpha}")
    terms = parse_terms(declared)
    offered = list(effects) if effects is not None else candidate_effects(terms)
    # One common first row for every model and candidate, so that RSS values compare.
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in offered])
    declared_model = _fit(x, y, terms, lag)
    rounds: list[Round] = []
    for _ in range(max_rounds):
        remaining = [e for e in offered if any(t not in terms for t in e.terms)]
        step = _round(x, y, terms, remaining, lag, alpha)
        rounds.append(step)
        if step.added is None:
            break
        terms = terms + parse_terms(step.added.terms)
    return Refinement(declared_model, _fit(x, y, terms, lag), tuple(rounds))


def _fit(x: np.ndarray, y: np.ndarray, terms: tuple[Term, ...], lag: int) -> NARX:
    # fit_narx starts each record at the terms' own largest lag; trimming x and y to the common
    # first row makes every model see the same equations.
    offset = lag - max_lag(terms)
    return fit_narx([(x[offset:], y[offset:])], terms)


def _round(
    x: np.ndarray, y: np.ndarray, terms: tuple[Term, ...], effects: Sequence[Effect], lag: int, alpha: float
) -> Round:
    Phi, target = regressor_matrix(terms, x, y, lag)
    scale = np.linalg.norm(Phi, axis=0)
    Q, _ = linalg.qr(Phi / scale, mode="economic")
    residual = target - Q @ (Q.T @ target)
    n_obs, n_par = Phi.shape
    candidates = [[t for t in e.terms if t not in terms] for e in effects]
    total = sum(len(c) for c in candidates)
    level = alpha / max(total, 1)
    scores = []
    for effect, family in zip(effects, candidates, strict=True):
        columns, _ = regressor_matrix(family, x, y, lag)
        columns = columns / np.linalg.norm(columns, axis=0)
        columns -= Q @ (Q.T @ columns)
        scores.append(_forward(effect.name, family, columns, residual, n_obs - n_par, level))
    significant = [s for s in scores if s.significant]
    added = max(significant, key=lambda s: s.explained) if significant else None
    rms = float(np.sqrt(np.mean(residual**2)))
    return Round(rms, level, total, tuple(scores), added)


def _forward(
    name: str, family: Sequence[Term], columns: np.ndarray, residual: np.ndarray, dof: int, level: float
) -> EffectScore:
    """Greedy selection within one family by error reduction ratio, each term after its F test."""
    rss0 = rss = float(residual @ residual)
    e = residual.copy()
    W = columns.copy()
    chosen: list[int] = []
    f_values: list[float] = []
    p_values: list[float] = []
    while len(chosen) < len(family):
        norms = np.einsum("ij,ij->j", W, W)
        usable = norms > 1e-10  # columns (nearly) in the span of the model or of chosen terms
        usable[chosen] = False
        if not usable.any():
            break
        gains = np.where(usable, (W.T @ e) ** 2 / np.where(usable, norms, 1.0), -1.0)
        best = int(np.argmax(gains))
        new_rss = rss - gains[best]
        remaining_dof = dof - len(chosen) - 1
        f_value = gains[best] / (new_rss / remaining_dof)
        p_value = float(special.fdtrc(1, remaining_dof, f_value))
        if p_value >= level:
            break
        w = W[:, best] / np.sqrt(norms[best])
        e -= w * (w @ e)
        W -= np.outer(w, w @ W)
        chosen.append(best)
        f_values.append(float(f_value))
        p_values.append(p_value)
        rss = new_rss
    return EffectScore(
        name,
        1.0 - rss / rss0 if rss0 > 0 else 0.0,
        tuple(family[i].name for i in chosen),
        tuple(f_values),
        tuple(p_values),
    )
