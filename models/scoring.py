"""Scoring candidate effects against a model's one-step residual (SPEC §7, the loop's step 2).

Every named candidate effect — a family of regressors with a physical meaning
(:mod:`models.effects`) — is scored by how much of the residual e it explains. Within a family,
regressors enter greedily by their error reduction ratio against e, each after a partial F test

    F = (RSS_before − RSS_after) / (RSS_after / (N − p)) ~ F(1, N − p),

at the Bonferroni level α / M, where M counts every candidate regressor of every family in the
round: the more regressors are on offer, the stronger the evidence each must bring. Candidate
columns are orthogonalised against the current regressors first (e is orthogonal to them
already), so each score is the reduction of the residual sum of squares that refitting with the
new regressors would achieve; the Bayesian information criterion's change
N·ln(RSS_after/RSS_before) + k·ln N ranks the significant effects.

The estimation data may be several records: their equations are stacked, and no lag (of the
signals or of the residual) reaches across the boundary between two.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from itertools import chain, islice, pairwise
from typing import Any

import numpy as np
import scipy
from scipy import linalg, special

from models.effects import (
    RECTIFIED,
    Effect,
    SearchInput,
    magnitude_direction,
    offset_direction,
    periodic_terms,
    reads_magnitude,
    records_output_limits,
    saturation_direction,
)
from models.narmax import fit_narmax, invertible
from models.narx import NARX, Saturation, fit_narx, fitted_rows
from models.regression import (
    Workers,
    column_norms,
    divided_columns,
    orthogonal_part,
    span_basis,
    subtract_outer,
)
from models.terms import Term, max_lag, parse_terms, record_origins, stacked_regressors

Records = Sequence[tuple[np.ndarray, np.ndarray]]
Saturating = tuple[tuple[float, float], Saturation]  # a saturating model's limits, and how
# The kinds of effect whose regressors a search over the residual finds (Effect): each takes
# tenths of a second where the others take milliseconds.
SEARCHED = frozenset({"combined", "estimated", "periodic"})
NOISE_LAGS_OFFERED = 4  # moving-average lags a round offers beyond those the model has
# The extended least-squares iterate the rounds take: it settles within this on simulated records,
# not always on long measured ones, whose fits the cap stops short of its fixed point (``converged``
# false); the loop's figures are those of the iterate at the cap (models/narmax.py says why the
# fixed point is not the prediction error's minimum either).
NARMAX_ITERATIONS = 30
# Scorings a loop keeps (ScoringKept): a round's own and the structure its look ahead chose.
KEPT_MODELS = 2


@dataclass(frozen=True)
class EffectScore:
    """How much of the residual an effect explains with its significant regressors.

    ``explained`` is the fraction of the residual sum of squares removed by the k regressors that
    entered, each with its partial F statistic and p-value, and ``bic_change`` the change of the
    Bayesian information criterion, n·ln(1 − explained) + p·ln n, p the parameters the model
    gains: one a term (a combination's regressor stands for the monomials spanning it, which the
    model then estimates freely, so a family of one regressor and thirty terms is not ranked as
    one of a single term). ``terms`` are the terms adding the effect puts into the
    model (for moving-average noise, the e[t-k] it adds, and ``noise_lags`` the model's
    moving-average order once it is added). ``ranked`` lists every candidate's terms in the order
    of their error reduction, significant or not: what a simulation-error check may try.
    """

    name: str
    description: str
    explained: float
    bic_change: float
    terms: tuple[str, ...]
    f_statistics: tuple[float, ...]
    p_values: tuple[float, ...]
    noise_lags: int = 0
    ranked: tuple[tuple[str, ...], ...] = ()

    @property
    def significant(self) -> bool:
        return bool(self.f_statistics)


@dataclass(frozen=True)
class Scores:
    """One round's scoring: the residual's RMS, the level α / M used, M, and every effect's score."""

    residual_rms: float
    level: float
    candidates: int
    scores: tuple[EffectScore, ...]


def fit_model(
    records: Records,
    terms: tuple[Term, ...],
    noise_lags: int,
    lag: int,
    t0: Sequence[int] | int = 0,
    saturating: Saturating | None = None,
    rectified: bool = False,
) -> tuple[NARX, np.ndarray]:
    """The model on rows t = lag … N−1 of each record: a NARX (``saturating`` at its limits, in
    its way; ``rectified``, its least-squares fit on the readings, :mod:`models.narx`), or with
    ``noise_lags`` a NARMAX's process part and moving-average coefficients."""
    limits, saturation = saturating or (None, "state")
    # The fits start a record at the terms' own largest lag; trimming x and y to the common
    # first row makes the model see the same equations as the candidates it is compared with.
    offset = lag - max_lag(terms)
    trimmed = [(x[offset:], y[offset:]) for x, y in records]
    origins = [origin + offset for origin in record_origins(t0, len(records))]
    if noise_lags:
        narmax = fit_narmax(trimmed, terms, noise_lags, max_iter=NARMAX_ITERATIONS, t0=origins)
        process = replace(narmax.process, output_limits=limits, saturation=saturation, rectified=rectified)
        return process, invertible(narmax.noise)
    return replace(fit_narx(trimmed, terms, origins, limits, saturation), rectified=rectified), np.empty(0)


def score_effects(
    records: Records,
    terms: tuple[Term, ...],
    noise_lags: int,
    effects: Sequence[Effect],
    alpha: float,
    rank: bool = False,
    saturating: Saturating | None = None,
    workers: Workers = map,
    threads: Workers = map,
    kept: ScoringKept | None = None,
    lag: int | None = None,
    level: float | None = None,
) -> Scores:
    """Score each effect against the current model's residual on the estimation records; with
    ``rank``, each score also ranks all the family's regressors (``EffectScore.ranked``). The
    searched families' candidate regressors are built by ``workers``
    (:data:`models.regression.Workers`), and the families tested by ``threads``, a map over
    threads of this process (the tests are numpy's work on columns of the records' length, too
    large to send to a process, and numpy lets go of the interpreter while it works): the same
    whichever. ``kept``, for a caller that scores the same model on the same records again
    (:class:`ScoringKept`): the model's equations and each family's candidates built then are
    taken from it, and what is built now is kept there. ``lag``: the equations' first row, by
    default :func:`first_row` of the model and ``effects``; a caller scoring some of a round's
    families gives the round's, and finds that round's scoring of the model in ``kept``.
    ``level``: the tests' level, by default α over every candidate regressor offered; a caller
    scoring a family beside a round's gives the round's."""
    # One common first row for the model and every candidate, so that the RSS values compare.
    lag = first_row(terms, effects) if lag is None else lag
    key = (tuple(terms), noise_lags, saturating, lag, alpha)
    model = kept.model(key) if kept is not None else None
    if model is None:
        fits = kept.fits if kept is not None else None
        model = _model_scored(records, terms, noise_lags, lag, saturating, fits)
        if kept is not None:
            kept.keep(key, model)
    build = partial(
        _candidates,
        terms=terms,
        noise_lags=noise_lags,
        theta=model.theta,
        residual=model.every_row,
        starts=stacked_starts(records, lag),
        alpha=alpha,
        records=records,
        lag=lag,
    )
    # The families found by a search over the residual (a combination of lags, an estimated
    # power, the periodogram's lines) take nearly all of a round's building: they go to the
    # workers first, and the others, fixed functions of the signals, are built here meanwhile;
    # each family is projected off the model as it comes, and tested once all are in (the level
    # counts every candidate).
    unbuilt = [i for i, effect in enumerate(effects) if effect not in model.candidates]
    searched = [i for i in unbuilt if effects[i].kind in SEARCHED]
    found = workers(build, [effects[i] for i in searched])
    built = chain(
        ((i, build(effects[i])) for i in unbuilt if i not in searched),
        zip(searched, found, strict=True),
    )
    for i, (labels, columns) in built:
        model.candidates[effects[i]] = _projected(labels, columns[model.inside], model.Q)
    candidates = {i: model.candidates[effect] for i, effect in enumerate(effects)}
    total = sum(columns.shape[1] for _, columns in candidates.values())
    level = alpha / max(total, 1) if level is None else level
    residual = model.residual
    scores = _tested(
        effects, candidates, residual, model.own_past, model.dof, level, rank, noise_lags, threads
    )
    return Scores(float(np.sqrt(np.mean(residual**2))), level, total, scores)


def first_row(terms: Sequence[Term], effects: Sequence[Effect]) -> int:
    """The first row of a scoring's equations: the longest lag of the model and of the families'
    terms."""
    return max([max_lag(terms)] + [max_lag(e.terms) for e in effects if e.terms])


@dataclass
class _ModelScored:
    """What :func:`score_effects` builds of the model itself, the same for every family: the
    orthonormal basis Q of its regressors over the rows it is fitted on (``inside`` of every
    row), its residual there and over every row (zero outside), its parameters, the degrees of
    freedom left, the residual's own recent past off the model, and each family's candidates
    projected off it, by family."""

    Q: np.ndarray
    residual: np.ndarray
    every_row: np.ndarray
    inside: np.ndarray
    theta: np.ndarray
    dof: int
    own_past: np.ndarray
    candidates: dict[Effect, tuple[list[tuple[str, ...]], np.ndarray]] = field(default_factory=dict)


def _model_scored(
    records: Records,
    terms: tuple[Term, ...],
    noise_lags: int,
    lag: int,
    saturating: Saturating | None,
    fits: FitsOnAll | None = None,
) -> _ModelScored:
    """The model's part of :func:`score_effects`, no family built yet; ``fits`` as for
    :func:`_model_equations`."""
    Phi, target, starts, inside = _model_equations(records, terms, noise_lags, lag, saturating, fits)
    scale = column_norms(Phi)
    Q, R = linalg.qr(divided_columns(Phi, scale), mode="economic", overwrite_a=True)
    projection = Q.T @ target
    residual = target - Q @ projection
    theta = (linalg.solve_triangular(R, projection) / scale)[: len(terms)]
    n_obs, n_par = Phi.shape
    every_row = np.zeros(inside.size)
    every_row[inside] = residual
    # A smooth residual predicts itself, and a coloured one makes spurious regressors look
    # significant: effects of the signals are judged after the residual's own recent past has
    # had its say, and moving-average noise after the signals' effects have had theirs. Each
    # is credited only with what the other cannot explain.
    own_past = _orthonormal(
        _lagged(residual, range(noise_lags + 1, noise_lags + 1 + NOISE_LAGS_OFFERED), starts), Q
    )
    return _ModelScored(Q, residual, every_row, inside, theta, n_obs - n_par, own_past)


# What fixes a least-squares fit on a loop's records (:func:`fit_model`'s arguments but the
# records): the terms, the moving-average order, the first row, the saturation and the rectifier.
FitKey = tuple[tuple[Term, ...], int, int, Saturating | None, bool]


class FitsOnAll:
    """The least-squares fits (:func:`fit_model`) a loop made on all its records, by what fixes
    each (:data:`FitKey`): a NARMAX's extended least squares iterates over every row of the
    records, and the comparison of the rounds' models on the held-out tails
    (:mod:`models.rounds_on_tails`) asks again for those the rounds' scorings made. A model and
    its noise coefficients a fit, kept for the loop's life; the records must stay the same (a
    loop's own)."""

    def __init__(self) -> None:
        self._fits: dict[FitKey, tuple[NARX, np.ndarray]] = {}

    def fitted(self, key: FitKey, fit: Callable[[], tuple[NARX, np.ndarray]]) -> tuple[NARX, np.ndarray]:
        """The fit kept under ``key``, made by ``fit`` and kept where there is none."""
        if key not in self._fits:
            self._fits[key] = fit()
        return self._fits[key]

    def get(self, key: FitKey) -> tuple[NARX, np.ndarray] | None:
        """The fit kept under ``key``, if one is."""
        return self._fits.get(key)


def fit_model_kept(
    records: Records,
    terms: tuple[Term, ...],
    noise_lags: int,
    lag: int,
    saturating: Saturating | None = None,
    rectified: bool = False,
    fits: FitsOnAll | None = None,
) -> tuple[NARX, np.ndarray]:
    """:func:`fit_model` on the ``records`` from their first samples, taken from ``fits`` where
    it holds this fit and kept there otherwise (fitted alone where ``fits`` is None): the one
    place that says what a kept fit is keyed by."""
    fit = partial(fit_model, records, terms, noise_lags, lag, saturating=saturating, rectified=rectified)
    if fits is None:
        return fit()
    return fits.fitted((tuple(terms), noise_lags, lag, saturating, rectified), fit)


class ScoringKept:
    """The models a loop scored last (:func:`score_effects`), their equations and the families'
    candidates built for them, for the loop's next scoring of one of them on the same records:
    the round after a look one round ahead (``models.refinement``) scores the structure the
    look scored, with the families it offered and more, and a round that goes on to the
    simulation criterion scores its model once more with every regressor ranked. Every family's
    candidates are a function of the model, the records, the common first row and the level α
    alone, so those built once serve again as they are, to the bit; the level α/M and the tests
    are made anew for the families offered. ``KEPT_MODELS`` at a time, the least recently asked
    for let go first: a round that looks ahead scores two structures of the next round and then
    its own model again (the hysteresis family ranked on it, ``models.round_criteria``), and
    with one kept the next round built again every family of the structure the look chose, its
    combination and parameter searches among them. A round's candidates take tens of megabytes:
    asked for a model not kept, the kept are cut to one fewer at once, before the other's arrays
    are made beside them. The records must stay the same for the kept's life (a loop's own)."""

    def __init__(self) -> None:
        self._models: dict[tuple[Any, ...], _ModelScored] = {}
        # The models' fits on all the records, kept beyond their scorings: small, and asked for
        # again after the rounds.
        self.fits = FitsOnAll()

    def model(self, key: tuple[Any, ...]) -> _ModelScored | None:
        """The model kept under ``key``, if it is kept (now the most recently asked for)."""
        model = self._models.pop(key, None)
        if model is not None:
            self._models[key] = model
            return model
        self._make_room()
        return None

    def keep(self, key: tuple[Any, ...], model: _ModelScored) -> None:
        """Keep ``model`` (and what is built for it later) under ``key``, the least recently
        asked for of those kept let go where ``KEPT_MODELS`` are."""
        self._models.pop(key, None)
        self._make_room()
        self._models[key] = model

    def _make_room(self) -> None:
        """Let go of the least recently asked for until one more can be kept."""
        while len(self._models) >= KEPT_MODELS:
            del self._models[next(iter(self._models))]


def _model_equations(
    records: Records,
    terms: tuple[Term, ...],
    noise_lags: int,
    lag: int,
    saturating: Saturating | None,
    fits: FitsOnAll | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The model's regressors and target on the rows t = lag … N−1 of each record that it is
    fitted on, each record's first of those rows (and the end), and which of every row they are;
    with ``noise_lags``, the NARMAX's lagged innovations beside its regressors, its fit taken
    from and kept in ``fits`` where given."""
    Phi, target, starts = stacked_regressors(terms, records, lag)
    # A saturating model's equations on (or, for a sensor, reading) its limits are left out; the
    # candidates are built on every row and masked alike.
    inside = np.ones(target.size, dtype=bool)
    if saturating is not None:
        inside = np.concatenate([fitted_rows(y, lag, *saturating) for _, y in records])
        Phi, target = Phi[inside], target[inside]
        starts = np.concatenate(([0], np.cumsum([int(inside[a:b].sum()) for a, b in pairwise(starts)])))
    if noise_lags:  # pseudo-linear regression on the NARMAX's own innovations
        process, noise = fit_model_kept(records, terms, noise_lags, lag, saturating, fits=fits)
        residual = target - Phi @ process.theta
        innovations = np.concatenate(
            [
                scipy.signal.lfilter([1.0], np.concatenate(([1.0], noise)), residual[a:b])
                for a, b in pairwise(starts)
            ]
        )
        Phi = np.hstack([Phi, _lagged(innovations, range(1, noise_lags + 1), starts)])
    return Phi, target, starts, inside


def _tested(
    effects: Sequence[Effect],
    candidates: dict[int, tuple[list[tuple[str, ...]], np.ndarray]],
    residual: np.ndarray,
    own_past: np.ndarray,
    dof: int,
    level: float,
    rank: bool,
    noise_lags: int,
    threads: Workers,
) -> tuple[EffectScore, ...]:
    """Each effect's score, in the order of ``effects``, from its ``candidates`` (by its
    index): the signals' effects tested by ``threads`` beside the residual's ``own_past``,
    moving-average noise then beside the columns they chose."""
    scores: dict[int, EffectScore] = {}
    explaining: list[np.ndarray] = []
    of_the_signals = [i for i, effect in enumerate(effects) if effect.kind != "noise"]
    tested = threads(
        lambda i: score_columns(effects[i], *candidates[i], residual, own_past, dof, level, rank),
        of_the_signals,
    )
    for index, (score, _, chosen_columns) in zip(of_the_signals, tested, strict=True):
        scores[index] = score
        explaining.append(chosen_columns)
    # The chosen columns are orthogonal to the model already (_projected): a basis of their span
    # is all the noise family's test needs.
    signals = span_basis(np.hstack([np.empty((len(residual), 0)), *explaining]))
    for index, effect in enumerate(effects):
        if effect.kind == "noise":
            labels, columns = candidates[index]
            score, chosen, _ = score_columns(effect, labels, columns, residual, signals, dof, level, rank)
            # The moving-average order becomes the longest lag that entered.
            scores[index] = replace(score, noise_lags=noise_lags + 1 + max(chosen) if chosen else 0)
    return tuple(scores[i] for i in range(len(effects)))


def stacked_starts(records: Records, lag: int) -> np.ndarray:
    """Each record's first row among the stacked rows t = lag … N−1 of every record (and the end)."""
    return np.cumsum([0] + [len(y) - lag for _, y in records])


def _lagged(series: np.ndarray, lags: Sequence[int], starts: np.ndarray) -> np.ndarray:
    """Columns series[t−k] for each k, zero before each record's first row."""
    columns = np.zeros((series.size, len(lags)))
    for first, last in pairwise(starts):
        for j, k in enumerate(lags):
            if k < last - first:
                columns[first + k : last, j] = series[first : last - k]
    return columns


def _orthonormal(columns: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """An orthonormal basis of the columns' part orthogonal to Q (empty for no columns)."""
    if columns.shape[1] == 0:
        return columns
    columns = orthogonal_part(columns / column_norms(columns), Q)
    basis, triangle = linalg.qr(columns, mode="economic")
    return basis[:, np.abs(np.diag(triangle)) > 1e-10]


def _projected(
    labels: list[tuple[str, ...]], columns: np.ndarray, Q: np.ndarray
) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """A family's candidate columns, each of unit norm, minus their projection on the model (Q)."""
    return labels, orthogonal_part(columns / column_norms(columns), Q)


def score_columns(
    effect: Effect,
    labels: list[tuple[str, ...]],
    columns: np.ndarray,
    residual: np.ndarray,
    given: np.ndarray,
    dof: int,
    level: float,
    rank: bool,
) -> tuple[EffectScore, list[int], np.ndarray]:
    """An effect's score against the residual once the model and ``given`` (orthonormal,
    orthogonal to the model) are accounted for, its ``columns`` already orthogonal to the model
    (:func:`_projected`); the indices of the columns it chose, and those columns."""
    chosen_from = columns
    columns = orthogonal_part(columns, given)
    target = residual - given @ (given.T @ residual)
    dof -= given.shape[1]
    if effect.kind == "periodic":
        tested = _in_quadrature(columns, target, dof, level, rank, _by_frequency(labels))
    else:
        # A searched family's parameters were chosen so that its columns together explain the
        # residual best: their joint F test would judge them on the fit that chose them. A law
        # whose exponent is searched beside integer laws of its signal enters as a block all the
        # same, its exponent counted among the block's parameters: its force reaches the sampled
        # output, as a fixed family's does, as a near-cancelling combination of neighbouring lags,
        # and where it stands in for an integer law and an effect beside it the round's test of
        # it against them (:func:`models.round_criteria.integer_law_first`) tells. Whatever a
        # family's search fitted to this residual (that exponent, a combination's direction and
        # the ratio of its powers) is counted among its first entry's parameters
        # (``Effect.searched``): a combination's one regressor, tested as one free column, passed
        # on clean records of a linear structure many times as often as the level allows.
        tested = _evidence_first(effect, columns, target, dof, level, rank)
    order, count, f_values, p_values, explained = tested
    chosen = order[:count]
    added = [label for i in chosen for label in labels[i]]
    n_obs = len(residual)
    bic = n_obs * float(np.log1p(-min(explained, 1 - 1e-300))) + len(added) * float(np.log(n_obs))
    score = EffectScore(
        effect.name,
        effect.description,
        explained,
        bic,
        tuple(added),
        f_values,
        p_values,
        ranked=tuple(labels[i] for i in order),
    )
    return score, chosen, chosen_from[:, chosen]


def _evidence_first(
    effect: Effect, columns: np.ndarray, target: np.ndarray, dof: int, level: float, rank: bool
) -> tuple[list[int], int, tuple[float, ...], tuple[float, ...], float]:
    """:func:`_forward` on a family's columns; for one whose own evidence comes first
    (``Effect.evidence_first``: its first column), that column alone where it passes its test,
    else the others."""
    if not effect.evidence_first or columns.shape[1] != 2:
        law = bool(effect.integer_laws)
        return _forward(columns, target, dof, level, rank, effect.kind == "terms" or law, effect.searched)
    own = _forward(columns[:, :1], target, dof, level, rank)
    if own[1]:
        return own
    order, count, f_values, p_values, explained = _forward(
        columns[:, 1:], target, dof, level, rank, searched=effect.searched
    )
    return [i + 1 for i in order], count, f_values, p_values, explained


def _candidates(
    effect: Effect,
    terms: tuple[Term, ...],
    noise_lags: int,
    theta: np.ndarray,
    residual: np.ndarray,
    starts: np.ndarray,
    alpha: float,
    records: Records,
    lag: int,
) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """The regressors an effect is tested with, and for each the term names it adds if it enters."""
    if effect.kind == "output_shift":
        direction = np.concatenate([offset_direction(terms, theta, x, y, lag) for x, y in records])
        return [tuple(t.name for t in effect.terms)], direction[:, None]
    if effect.kind == "noise":
        lags = range(noise_lags + 1, noise_lags + 1 + NOISE_LAGS_OFFERED)
        return [(f"e[t-{k}]",) for k in lags], _lagged(residual, lags, starts)
    if effect.kind == "saturation":  # one regressor, the clip of the one-step prediction
        limits = records_output_limits(records)
        if limits is None:
            return [], np.empty((len(residual), 0))
        label = f"output_limits({limits[0]!r},{limits[1]!r})"
        return [(label,)], saturation_direction(
            np.concatenate([y[lag:] for _, y in records]) - residual, limits
        )[:, None]
    if effect.kind == "rectified":  # one regressor, the magnitude of the one-step prediction
        measured = np.concatenate([y[lag:] for _, y in records])
        direction = magnitude_direction(measured - residual)
        # A prediction that never goes below zero leaves the regressor nothing: not tested.
        if not reads_magnitude(measured) or not np.any(direction):
            return [], np.empty((len(residual), 0))
        return [(RECTIFIED,)], direction[:, None]
    if effect.kind == "combined" and effect.combine is not None:
        # A combination of lags, sought on the first record like an estimated parameter, is a
        # fixed function of the lags: its regressor is built on every record.
        spanning, column = effect.combine(records, residual, terms, lag)
        if not spanning:
            return [], np.empty((len(residual), 0))
        if effect.evidence_first:  # the constant first, tested alone (score_columns)
            labels = [(Term().name,), tuple(t.name for t in spanning)]
            return labels, np.column_stack([np.ones_like(column), column])
        return [tuple(t.name for t in spanning)], column[:, None]
    if effect.kind == "estimated" and effect.find is not None:
        # Parameters (a power, a width) estimated on the first record, tested on all.
        x0, y0 = records[0]
        found = effect.find(SearchInput(x0, y0, residual[: starts[1]], terms, lag))
    elif effect.kind == "periodic":
        # A sinusoid of t is phase-locked to the record it was found in: with several records and
        # no common time base it would mean nothing on the next one.
        found = periodic_terms(residual, alpha, records[0][0]) if len(records) == 1 else ()
    else:
        found = effect.terms
    new = [t for t in found if t not in terms]
    if not new:
        return [], np.empty((len(residual), 0))
    return [(t.name,) for t in new], stacked_regressors(new, records, lag)[0]


def _by_frequency(labels: Sequence[tuple[str, ...]]) -> list[list[int]]:
    """The indices of a periodic family's columns (each one sinusoid's sine or cosine), grouped
    by frequency."""
    groups: dict[float | None, list[int]] = {}
    for index, (name,) in enumerate(labels):
        groups.setdefault(parse_terms([name])[0].factors[0].frequency, []).append(index)
    return list(groups.values())


def _in_quadrature(
    columns: np.ndarray, residual: np.ndarray, dof: int, level: float, rank: bool, groups: list[list[int]]
) -> tuple[list[int], int, tuple[float, ...], tuple[float, ...], float]:
    """:func:`_forward` for a periodic disturbance, whose sine and cosine at one frequency enter
    together or not at all: each frequency's pair in turn, the one that explains most of what
    the pairs before it left first, each by the pair's joint F test at ``level``.

    A disturbance's phase is a parameter of the one effect, as its frequency is, not a choice
    between two regressors. Tested one wave at a time the family entered as whichever of sine
    and cosine the record's time origin favoured, the other left out as not significant alone,
    and the model lacked the disturbance it had named (on the rig with a 12.5 Hz force, a cosine
    alone that ran free worse than the start where the pair ran free better)."""
    rss0 = rss = float(residual @ residual)
    e, basis = residual.copy(), np.empty((len(residual), 0))
    order: list[int] = []
    chosen, f_values, p_values = 0, [], []
    left = list(groups)
    while left:
        parts = [_orthonormal(columns[:, group], basis) for group in left]
        falls = [float(np.sum((part.T @ e) ** 2)) for part in parts]
        best = int(np.argmax(falls))
        group, part, fall = left.pop(best), parts[best], falls[best]
        size, remaining_dof = part.shape[1], dof - len(order) - part.shape[1]
        if chosen == len(order) and size and remaining_dof >= 1:
            f_value = np.inf if rss - fall <= 0 else fall / size / ((rss - fall) / remaining_dof)
            p_value = float(special.fdtrc(size, remaining_dof, f_value))
            if p_value < level:
                chosen += len(group)
                f_values += [float(f_value)] * len(group)
                p_values += [p_value] * len(group)
                rss -= fall
        if chosen < len(order) + len(group) and not rank:
            break
        order += group
        e -= part @ (part.T @ e)
        basis = np.hstack([basis, part])
    explained = 1.0 - rss / rss0 if chosen and rss0 > 0 else 0.0
    return order, chosen, tuple(f_values), tuple(p_values), explained


def _forward(
    columns: np.ndarray,
    residual: np.ndarray,
    dof: int,
    level: float,
    rank: bool,
    blocks: bool = False,
    searched: int = 0,
) -> tuple[list[int], int, tuple[float, ...], tuple[float, ...], float]:
    """Greedy selection within one family by error reduction ratio, each column after its F test.

    With ``blocks``, where the family's first column fails its test alone, the columns after it
    in the greedy order (each the best given those before) are tested with it as a block, by
    their joint F test at the same level, and the smallest block that passes enters whole. A
    force of the velocity reaches a sampled output as the difference of its values at
    neighbouring lags: each lag alone explains little of the residual, their near-cancelling
    combination most of it (on the 2-DOF rig with quadratic damping, dy·|dy| at each lag alone
    was not significant while the four together explained nine tenths of the residual). Once a
    family has entered, each further column is tested alone: a block after it would let weak
    columns in on a strong one's back (on the DC motor the generic polynomial took twice the
    terms and ran free worse).

    ``searched``: the family's parameters searched on this residual (an exponent, a combination of
    lags), counted among the parameters of its first entry's test, single column or block: they
    were fitted to the same residual the test reads.

    Returns the columns in the greedy order (every usable one if ``rank``, else the chosen ones),
    how many of the first passed their tests (the chosen ones), their F statistics and p-values
    (a block's own for each of its columns), and the fraction of the residual sum of squares the
    chosen ones explain.
    """
    # The greedy order is taken only as far as the tests read it (all of it where ``rank``): a
    # family of a few hundred columns whose first fails stops there.
    steps = _greedy(columns, residual)
    rss0 = float(residual @ residual)
    order: list[int] = []
    remaining = [rss0]

    def reach(count: int) -> None:
        for best, rss in islice(steps, max(count - len(order), 0)):
            order.append(best)
            remaining.append(rss)

    chosen = 0
    f_values: list[float] = []
    p_values: list[float] = []
    while True:
        largest = columns.shape[1] if blocks and chosen == 0 else 1
        block = _entering_block(remaining, reach, chosen, dof, level, largest, searched if chosen == 0 else 0)
        if block is None:
            break
        size, f_value, p_value = block
        chosen += size
        f_values += [f_value] * size
        p_values += [p_value] * size
    explained = 1.0 - remaining[chosen] / rss0 if chosen and rss0 > 0 else 0.0
    if rank:
        reach(columns.shape[1])
    return (order if rank else order[:chosen]), chosen, tuple(f_values), tuple(p_values), explained


def _greedy(columns: np.ndarray, residual: np.ndarray) -> Iterator[tuple[int, float]]:
    """The usable columns in the greedy order of error reduction (each the best given those
    before), one at a time as asked for, each with the residual sum of squares after it."""
    rss = float(residual @ residual)
    e = residual.copy()
    W = columns.copy()
    order: list[int] = []
    while len(order) < W.shape[1]:
        norms = np.einsum("ij,ij->j", W, W)
        usable = norms > 1e-10  # columns (nearly) in the span of the model or of chosen ones
        usable[order] = False
        if not usable.any():
            break
        gains = np.where(usable, (W.T @ e) ** 2 / np.where(usable, norms, 1.0), -1.0)
        best = int(np.argmax(gains))
        w = W[:, best] / np.sqrt(norms[best])
        e -= w * (w @ e)
        subtract_outer(W, w, w @ W)
        order.append(best)
        rss -= float(gains[best])
        yield best, rss


def _entering_block(
    remaining: Sequence[float],
    reach: Callable[[int], None],
    chosen: int,
    dof: int,
    level: float,
    largest: int,
    searched: int = 0,
) -> tuple[int, float, float] | None:
    """The smallest block, of at most ``largest`` columns, of the greedy order's next columns
    after the ``chosen`` ones that passes its joint F test at ``level``, as (its size, F,
    p-value); None where none does. ``remaining``: the residual sum of squares before the first
    column and after each, as far as ``reach`` (n) has taken the greedy order (its first n
    columns, or all that are usable): a block is asked for one column more only where the
    smaller one failed. ``searched``: parameters fitted with the block, beside its columns."""
    for size in range(1, largest + 1):
        reach(chosen + size)
        if len(remaining) <= chosen + size:  # no usable column left
            return None
        after = remaining[chosen + size]
        parameters = size + searched
        remaining_dof = dof - chosen - parameters
        if remaining_dof < 1:
            return None
        if after <= 0:  # the block explains the whole residual
            return size, np.inf, 0.0
        f_value = (remaining[chosen] - after) / parameters / (after / remaining_dof)
        p_value = float(special.fdtrc(parameters, remaining_dof, f_value))
        if p_value < level:
            return size, float(f_value), p_value
    return None
