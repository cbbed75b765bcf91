"""Closing the loop (SPEC §7): residual → the effect the model lacks → refined model.

Starting from a declared structure, each round

1. fits the current model on the estimation data and takes its residual e (a NARX by least
   squares; once moving-average noise terms are in, a NARMAX by extended least squares, whose
   lagged innovations join the regressors);
2. scores every named candidate effect — a family of regressors with a physical meaning
   (:mod:`models.effects`) — by how much of e it explains. Within a family, regressors enter
   greedily by their error reduction ratio against e, each after a partial F test
   F = (RSS_before − RSS_after) / (RSS_after / (N − p)) ~ F(1, N − p),
   at the Bonferroni level α / M, where M counts every candidate regressor of every family in
   the round: the more regressors are on offer, the stronger the evidence each must bring;
3. adds the significant effect with the largest fall of the Bayesian information criterion
   (which charges each effect for its size), and repeats until no family has a significant
   regressor.

Candidate columns are orthogonalised against the current regressors first (e is orthogonal to
them already), so each score is the reduction of the residual sum of squares that refitting
with the new regressors would achieve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, get_args

import numpy as np
from scipy import linalg, signal, special

from models.assessment import Assessment, assess, assessment_dict, check_test_length
from models.effects import (
    Effect,
    candidate_effects,
    offset_direction,
    offset_terms,
    output_limits,
    periodic_terms,
    saturation_direction,
    unused,
)
from models.errors import InputError
from models.narmax import fit_narmax, invertible
from models.narx import NARX, Saturation, fit_narx, fitted_rows
from models.terms import Term, max_lag, parse_terms, regressor_matrix

DEFAULT_ALPHA = 0.01
MAX_ROUNDS = 10
NOISE_LAGS_OFFERED = 4  # moving-average lags a round offers beyond those the model has
# Extended least squares settles in 13–15 iterations on simulated records; on long measured ones
# its last digits wander for longer without changing what the loop decides.
NARMAX_ITERATIONS = 30
GUARD_SAMPLES = 10_000  # estimation samples whose free run an added effect must not make worse
Saturating = tuple[tuple[float, float], Saturation]  # a saturating model's limits, and how


@dataclass(frozen=True)
class EffectScore:
    """How much of the residual an effect explains with its significant regressors.

    ``explained`` is the fraction of the residual sum of squares removed and ``bic_change`` the
    change of the Bayesian information criterion N·ln(RSS_after/RSS_before) + k·ln N for the k
    regressors that entered, each with its partial F statistic and p-value; ``terms`` are the
    terms adding the effect puts into the model (for moving-average noise, the e[t-k] it adds,
    and ``noise_lags`` the model's moving-average order once it is added).
    """

    name: str
    description: str
    explained: float
    bic_change: float
    terms: tuple[str, ...]
    f_statistics: tuple[float, ...]
    p_values: tuple[float, ...]
    noise_lags: int = 0

    @property
    def significant(self) -> bool:
        return bool(self.f_statistics)


@dataclass(frozen=True)
class Round:
    """One round of the loop: every effect's score, the level used, and the effect added (if any)."""

    residual_rms: float
    level: float  # the Bonferroni-corrected significance level α / M
    candidates: int  # M
    scores: tuple[EffectScore, ...]
    added: EffectScore | None
    # Significant effects passed over, best first, because adding them made the model's free
    # run on the estimation data worse (or diverge).
    rejected: tuple[str, ...] = ()


@dataclass(frozen=True)
class Refinement:
    """The declared and refined models and the rounds that led from one to the other.

    ``noise`` holds the refined model's moving-average coefficients c_1 … c_q (empty unless
    moving-average noise was added; ``refined`` is then the process part of a NARMAX).
    """

    declared: NARX
    refined: NARX
    noise: np.ndarray = field(default_factory=lambda: np.empty(0))
    rounds: tuple[Round, ...] = field(default=())

    @property
    def effects_added(self) -> tuple[EffectScore, ...]:
        return tuple(r.added for r in self.rounds if r.added is not None)


@dataclass(frozen=True)
class RefinementReport:
    """A refinement with the declared and refined models' errors on held-out data."""

    refinement: Refinement
    before: Assessment
    after: Assessment

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: effects added in order with their evidence, errors before and after,
        and both models' terms and parameters. Non-finite numbers (a diverged free run) become None."""
        result = self.refinement
        return {
            "declared": _model_dict(result.declared),
            "effects_added": [
                {
                    "name": score.name,
                    "description": score.description,
                    "terms": list(score.terms),
                    "evidence": {
                        "explained_fraction": score.explained,
                        "bic_change": score.bic_change,
                        "residual_rms_before": step.residual_rms,
                        "f_statistics": list(score.f_statistics),
                        "p_values": list(score.p_values),
                        "level": step.level,
                        "candidate_terms": step.candidates,
                    },
                }
                for step in result.rounds
                if (score := step.added) is not None
            ],
            "before": assessment_dict(self.before),
            "after": assessment_dict(self.after),
            "refined": _model_dict(result.refined) | {"noise_ma": result.noise.tolist()},
        }


def refine_record(
    x: np.ndarray,
    y: np.ndarray,
    declared: Sequence[str | Term],
    estimation: tuple[int, int],
    test: tuple[int, int],
    initial: int = 0,
    alpha: float = DEFAULT_ALPHA,
    fs: float | None = None,
) -> RefinementReport:
    """Refine on samples ``estimation`` = (a, b) of one record, assess both models on ``test``.

    The first ``initial`` test samples only start the predictions (benchmark protocols
    prescribe such a start, e.g. 50 samples for Silverbox).
    """
    check_parts(len(x), declared, estimation, test, initial)
    a, b = estimation
    c, d = test
    result = refine(x[a:b], y[a:b], declared, alpha=alpha)
    return RefinementReport(
        result,
        assess(result.declared, x[c:d], y[c:d], initial, fs, c - a),
        assess(result.refined, x[c:d], y[c:d], initial, fs, c - a, result.noise),
    )


def check_parts(
    n: int,
    declared: Sequence[str | Term],
    estimation: tuple[int, int],
    test: tuple[int, int],
    initial: int = 0,
) -> None:
    """Refuse estimation and test parts that do not fit a record of ``n`` samples, or a test part
    too short to judge the models on: checked before the loop, which takes far longer."""
    for label, (first, last) in (("estimation", estimation), ("test", test)):
        if not 0 <= first < last <= n:
            raise InputError(f"the {label} samples {first}:{last} do not lie within the record's {n} samples")
    if initial < 0:
        raise InputError(f"the initial samples must be 0 or more, got {initial}")
    check_test_length(test[1] - test[0], max(initial, max_lag(parse_terms(declared))))


def _model_dict(model: NARX) -> dict[str, Any]:
    limits = model.output_limits
    # [output-side effects hook] the limits a saturating model clips to (None: none).
    return {
        "terms": model.term_names,
        "theta": model.theta.tolist(),
        "output_limits": None if limits is None else [v if np.isfinite(v) else None for v in limits],
        "saturation": None if limits is None else model.saturation,
    }


def refine(
    x: np.ndarray,
    y: np.ndarray,
    declared: Sequence[str | Term],
    effects: Sequence[Effect] | None = None,
    alpha: float = DEFAULT_ALPHA,
    max_rounds: int = MAX_ROUNDS,
) -> Refinement:
    """Refine the declared structure on estimation data (x, y) until no effect is significant.

    ``effects`` are the families on offer, by default :func:`models.effects.candidate_effects`
    of the declared terms: sized to the declared lags, so that the loop explains the residual
    with the declared dynamics rather than by lengthening them round after round. An offset's
    terms follow the model as it grows.
    """
    if not 0 < alpha < 1:
        raise InputError(f"alpha must lie in (0, 1), got {alpha}")
    terms = parse_terms(declared)
    families = list(effects) if effects is not None else candidate_effects(terms)
    _check_length(len(y), terms, families)
    declared_model, _ = _fit(x, y, terms, 0, max_lag(terms))
    refined, noise, noise_lags = declared_model, np.empty(0), 0
    free_run = _free_run_error(declared_model, x, y)
    saturating: Saturating | None = None
    rounds: list[Round] = []
    for _ in range(max_rounds):
        offered = unused([_follow(effect, terms) for effect in families], terms)
        # [output-side effects hook] a saturating model is not offered saturation again.
        offered = [e for e in offered if not (e.kind == "saturation" and saturating is not None)]
        if not offered:
            break
        step = _round(x, y, terms, noise_lags, offered, alpha, saturating)
        rejected: list[str] = []
        kinds = {e.name: e.kind for e in offered}
        for score in sorted((s for s in step.scores if s.significant), key=lambda s: s.bic_change):
            # [output-side effects hook] saturation adds output limits, not terms: of the state
            # or of the sensor, whichever simulates the estimation data better.
            saturation = kinds[score.name] == "saturation"
            options = (
                [(output_limits(y), how) for how in get_args(Saturation)] if saturation else [saturating]
            )
            new_terms = terms if score.noise_lags or saturation else terms + parse_terms(score.terms)
            new_lags = score.noise_lags or noise_lags
            fits = []
            for option in options:
                model, model_noise = _fit(x, y, new_terms, new_lags, max_lag(new_terms), option)
                fits.append((_free_run_error(model, x, y), model, model_noise, option))
            error, model, model_noise, new_saturating = min(fits, key=lambda fit: fit[0])
            if error <= free_run:
                step = replace(step, added=score, rejected=tuple(rejected))
                terms, noise_lags, free_run, saturating = new_terms, new_lags, error, new_saturating
                refined, noise = model, model_noise
                break
            rejected.append(score.name)
        else:
            rounds.append(replace(step, rejected=tuple(rejected)))
            break
        rounds.append(step)
    # The last effect accepted was fitted by its check: that fit is the refined model.
    return Refinement(declared_model, refined, noise, tuple(rounds))


def _free_run_error(model: NARX, x: np.ndarray, y: np.ndarray) -> float:
    """RMS error of the model's free run over the first ``GUARD_SAMPLES`` estimation samples
    (inf if it diverges): an effect that makes the model simulate worse is not added."""
    n = min(len(y), GUARD_SAMPLES)
    simulated = model.simulate(x[:n], y[:n])[model.max_lag :]
    error = float(np.sqrt(np.mean((simulated - y[model.max_lag : n]) ** 2)))
    return error if np.isfinite(error) else np.inf


def _check_length(n: int, terms: tuple[Term, ...], offered: Sequence[Effect]) -> None:
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in offered if e.terms])
    candidates = sum(len(e.terms) for e in offered)
    needed = lag + 2 * (len(terms) + candidates) + 1
    if n < needed:
        raise InputError(
            f"the estimation part has {n} samples; refining {len(terms)} terms with "
            f"{candidates} candidates needs at least {needed}"
        )


def _follow(effect: Effect, terms: tuple[Term, ...]) -> Effect:
    """An output-shift effect brings the terms the current model's offset would."""
    if effect.kind != "output_shift":
        return effect
    return Effect(effect.name, effect.description, offset_terms(terms), effect.kind)


def _fit(
    x: np.ndarray,
    y: np.ndarray,
    terms: tuple[Term, ...],
    noise_lags: int,
    lag: int,
    saturating: Saturating | None = None,
) -> tuple[NARX, np.ndarray]:
    """The model on rows t = lag … N−1: a NARX (``saturating`` at its limits, in its way), or
    with ``noise_lags`` a NARMAX's process part and moving-average coefficients."""
    limits, saturation = saturating or (None, "state")
    # The fits start a record at the terms' own largest lag; trimming x and y to the common
    # first row makes the model see the same equations as the candidates it is compared with.
    offset = lag - max_lag(terms)
    if noise_lags:
        narmax = fit_narmax(
            [(x[offset:], y[offset:])], terms, noise_lags, max_iter=NARMAX_ITERATIONS, t0=offset
        )
        return replace(narmax.process, output_limits=limits, saturation=saturation), invertible(narmax.noise)
    model = fit_narx([(x[offset:], y[offset:])], terms, offset, limits, saturation)
    return model, np.empty(0)


def _lagged(series: np.ndarray, lags: Sequence[int]) -> np.ndarray:
    """Columns series[t−k] for each k, zero before the series starts."""
    columns = np.zeros((series.size, len(lags)))
    for j, k in enumerate(lags):
        columns[k:, j] = series[: series.size - k]
    return columns


def _round(
    x: np.ndarray,
    y: np.ndarray,
    terms: tuple[Term, ...],
    noise_lags: int,
    effects: Sequence[Effect],
    alpha: float,
    saturating: Saturating | None = None,
) -> Round:
    # One common first row for the model and every candidate, so that the RSS values compare.
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in effects if e.terms])
    Phi, target = regressor_matrix(terms, x, y, lag)
    # [output-side effects hook] a saturating model's equations on (or, for a sensor, reading)
    # its limits are left out.
    inside = np.ones(len(target), dtype=bool) if saturating is None else fitted_rows(y, lag, *saturating)
    Phi, target = Phi[inside], target[inside]
    if noise_lags:  # pseudo-linear regression on the NARMAX's own innovations
        process, noise = _fit(x, y, terms, noise_lags, lag)
        innovations = signal.lfilter([1.0], np.concatenate(([1.0], noise)), target - Phi @ process.theta)
        Phi = np.hstack([Phi, _lagged(innovations, range(1, noise_lags + 1))])
    scale = np.linalg.norm(Phi, axis=0)
    Q, R = linalg.qr(Phi / scale, mode="economic")
    projection = Q.T @ target
    residual = target - Q @ projection
    theta = (linalg.solve_triangular(R, projection) / scale)[: len(terms)]
    n_obs, n_par = Phi.shape
    every_row = np.zeros(len(inside))
    every_row[inside] = residual
    candidates = [
        (labels, columns[inside])
        for labels, columns in (
            _candidates(e, terms, noise_lags, theta, every_row, alpha, x, y, lag) for e in effects
        )
    ]
    total = sum(columns.shape[1] for _, columns in candidates)
    level = alpha / max(total, 1)
    # A smooth residual predicts itself, and a coloured one makes spurious regressors look
    # significant: effects of the signals are judged after the residual's own recent past has
    # had its say, and moving-average noise after the signals' effects have had theirs. Each
    # is credited only with what the other cannot explain.
    own_past = _orthonormal(_lagged(residual, range(noise_lags + 1, noise_lags + 1 + NOISE_LAGS_OFFERED)), Q)
    scores: dict[int, EffectScore] = {}
    explaining: list[np.ndarray] = []
    for index, (effect, (labels, columns)) in enumerate(zip(effects, candidates, strict=True)):
        if effect.kind != "noise":
            score, _, chosen_columns = _score(
                effect, labels, columns, residual, Q, own_past, n_obs - n_par, level
            )
            scores[index] = score
            explaining.append(chosen_columns)
    signals = _orthonormal(np.hstack([np.empty((n_obs, 0)), *explaining]), Q)
    for index, (effect, (labels, columns)) in enumerate(zip(effects, candidates, strict=True)):
        if effect.kind == "noise":
            score, chosen, _ = _score(effect, labels, columns, residual, Q, signals, n_obs - n_par, level)
            # The moving-average order becomes the longest lag that entered.
            scores[index] = replace(score, noise_lags=noise_lags + 1 + max(chosen) if chosen else 0)
    ordered = [scores[i] for i in range(len(effects))]
    return Round(float(np.sqrt(np.mean(residual**2))), level, total, tuple(ordered), None)


def _orthogonal_part(columns: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Columns minus their projection on the orthonormal Q, by Gram–Schmidt applied twice: once
    loses orthogonality when a column lies nearly in Q's span, twice is enough (Kahan–Parlett)."""
    for _ in range(2):
        columns = columns - Q @ (Q.T @ columns)
    return columns


def _orthonormal(columns: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns' part orthogonal to Q (empty for no columns)."""
    if columns.shape[1] == 0:
        return columns
    columns = _orthogonal_part(columns / np.linalg.norm(columns, axis=0), Q)
    basis, triangle = linalg.qr(columns, mode="economic")
    return basis[:, np.abs(np.diag(triangle)) > 1e-10]


def _score(
    effect: Effect,
    labels: list[tuple[str, ...]],
    columns: np.ndarray,
    residual: np.ndarray,
    Q: np.ndarray,
    given: np.ndarray,
    dof: int,
    level: float,
) -> tuple[EffectScore, list[int], np.ndarray]:
    """An effect's score against the residual once the model (Q) and ``given`` (orthonormal,
    orthogonal to Q) are accounted for; the indices of the columns it chose, and those columns
    (orthogonal to Q)."""
    columns = _orthogonal_part(columns / np.linalg.norm(columns, axis=0), Q)
    chosen_from = columns.copy()
    columns = _orthogonal_part(columns, given)
    target = residual - given @ (given.T @ residual)
    chosen, f_values, p_values, explained = _forward(columns, target, dof - given.shape[1], level)
    added = [label for i in chosen for label in labels[i]]
    n_obs = len(residual)
    bic = n_obs * float(np.log1p(-min(explained, 1 - 1e-300))) + len(chosen) * float(np.log(n_obs))
    score = EffectScore(effect.name, effect.description, explained, bic, tuple(added), f_values, p_values)
    return score, chosen, chosen_from[:, chosen]


def _candidates(
    effect: Effect,
    terms: tuple[Term, ...],
    noise_lags: int,
    theta: np.ndarray,
    residual: np.ndarray,
    alpha: float,
    x: np.ndarray,
    y: np.ndarray,
    lag: int,
) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """The regressors an effect is tested with, and for each the term names it adds if it enters."""
    if effect.kind == "output_shift":
        return [tuple(t.name for t in effect.terms)], offset_direction(terms, theta, x, y, lag)[:, None]
    if effect.kind == "noise":
        lags = range(noise_lags + 1, noise_lags + 1 + NOISE_LAGS_OFFERED)
        return [(f"e[t-{k}]",) for k in lags], _lagged(residual, lags)
    # [output-side effects hook] saturation: one regressor, the clip of the one-step prediction.
    if effect.kind == "saturation":
        limits = output_limits(y)
        if limits is None:
            return [], np.empty((len(residual), 0))
        label = f"output_limits({limits[0]!r},{limits[1]!r})"
        return [(label,)], saturation_direction(y[lag:] - residual, limits)[:, None]
    # [output-side effects hook] one regressor fitted to the residual, spanned by the effect's terms.
    if effect.kind == "combined" and effect.combine is not None:
        spanning, column = effect.combine(x, y, residual, terms, lag)
        if not spanning:
            return [], np.empty((len(residual), 0))
        return [tuple(t.name for t in spanning)], column[:, None]
    # [output-side effects hook] terms whose parameters are estimated from the residual.
    if effect.kind == "estimated" and effect.find is not None:
        found = effect.find(x, y, residual, terms, lag)
    else:
        found = periodic_terms(residual, alpha) if effect.kind == "periodic" else effect.terms
    new = [t for t in found if t not in terms]
    if not new:
        return [], np.empty((len(residual), 0))
    return [(t.name,) for t in new], regressor_matrix(new, x, y, lag)[0]


def _forward(
    columns: np.ndarray, residual: np.ndarray, dof: int, level: float
) -> tuple[list[int], tuple[float, ...], tuple[float, ...], float]:
    """Greedy selection within one family by error reduction ratio, each column after its F test:
    the columns chosen in order, their F statistics and p-values, and the fraction of the
    residual sum of squares they explain."""
    rss0 = rss = float(residual @ residual)
    e = residual.copy()
    W = columns.copy()
    chosen: list[int] = []
    f_values: list[float] = []
    p_values: list[float] = []
    while len(chosen) < W.shape[1]:
        norms = np.einsum("ij,ij->j", W, W)
        usable = norms > 1e-10  # columns (nearly) in the span of the model or of chosen ones
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
    return chosen, tuple(f_values), tuple(p_values), (1.0 - rss / rss0 if rss0 > 0 else 0.0)
