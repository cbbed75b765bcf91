"""The linear start of the refinement loop where no structure is declared (:mod:`models.refinement`):
the ARX orders, input delay and constant that simulate the held-out data best for their size
(:func:`choose_linear`), and, where the outputs read as a magnitude, the orders the rectified
family starts from (:func:`rectified_orders`). Each candidate is judged on the three rotations of
the check split by consistent estimates (instrumental variables, output error), so that least
squares' bias does not buy needless orders, and a model the input barely drives is no start."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import NamedTuple

import numpy as np

from models.checking import CheckSplit, Segments, Structure
from models.effects import linear_terms, reads_magnitude, records_output_limits
from models.errors import InputError
from models.input_drive import feeds_through, input_drives
from models.narx import NARX
from models.refinement_report import Stage, told
from models.regression import Workers
from models.round_criteria import DEFAULT_ALPHA
from models.scoring import Records, Saturating
from models.terms import Term

MAX_LINEAR_ORDER = 10  # the largest order tried when no structure is declared
# A larger linear start is chosen only when it simulates the held-out data better than a smaller
# by this share and by more than their difference's spread across the check rotations
# (:func:`choose_linear`).
ORDER_GAIN = 0.05
# A linear start's response to the input alone must reach this share of the output's spread.
INPUT_SHARE = 0.1


def choose_linear(
    records: Records,
    max_order: int = MAX_LINEAR_ORDER,
    checks: CheckSplit | None = None,
    progress: Stage | None = None,
    workers: Workers = map,
    margin: float = ORDER_GAIN,
    rectified: bool = False,
) -> tuple[tuple[int, int, int], tuple[Term, ...]]:
    """The linear ARX structure y[t-1…t-n], x[t-d…t-d-n+1] (d = 0 or 1, n ≤ ``max_order``), with
    a constant or without, that simulates the held-out data best for its size.

    Every candidate is judged on the three rotations of the check split (each block of the
    estimation data held out once; from three records on, each record): fitted on the rest by
    instrumental variables and by output error, its figure the mean over the rotations of the
    better one's free-run RMS over the held-out parts (:func:`_rotation_figures`: least squares'
    bias would favour needlessly high orders). A model the input barely drives is no start
    (:func:`_is_start`): on a rig record with a large dead zone, least squares' best predictor of
    order 2 extrapolates the output's own past, y[t] ≈ 2y[t-1] − y[t-2]. Nor, as a rule, is one
    whose input coefficients are not significant (:func:`_smallest_driven`): one whose input lags
    stop short of the input's delay. Of the rest (of all,
    where the input drives none), the smallest is chosen whose figure is within ``margin``
    (relative) of the best, both raised for their size as the Bayesian information criterion
    raises them (:func:`_size_penalty`: on a few hundred samples a larger model's small gain is
    no reason), or above the best's by no more than the standard error of their difference across
    the rotations, or not above it on every rotation: for the loop's start, an effect the linear
    model lacks lowers the free run of larger orders a little and unevenly (the best linear
    approximation of the nonlinearity), not by a new mode. A baseline to monitor a structure by
    wants the model that simulates best, ``margin`` 0.

    **The constant.** The orders chosen without a constant are judged with one too, and every
    order with one where it pays (:func:`_with_constant`).

    **Plateaus.** Where the records' output plateaus at its range ends, every candidate is
    judged as a clipping sensor's model (:func:`_sensor_limits`).

    **Rectified.** With ``rectified``, every candidate is judged as a rectified model, its
    recursion read through a sensor of its magnitude (:mod:`models.narx`): the orders the
    rectified-output family starts from (:func:`rectified_orders`).

    Returns (n, n, d) and the terms; ``progress`` is told each candidate as its figures are read,
    ``workers`` fit them (:data:`models.regression.Workers`).
    """
    if max_order < 1:
        raise InputError(f"the largest linear order must be 1 or more, got {max_order}")
    checks = checks or CheckSplit.of(records)
    folds = [checks, *(CheckSplit.of(records, fold) for fold in (0, 2))]
    tell = told(progress)
    orders = [(n, d) for d in (1, 0) for n in range(1, max_order + 1)]
    samples = sum(len(y) for _, y in records)
    # The loop's level shared among every candidate's test, with a constant and without: on a
    # record of the rig, x[t-3]'s chance correlation with x[t-4] made ARX(3, 3)'s input
    # coefficients pass at the loop's level alone.
    level = DEFAULT_ALPHA / (2 * len(orders))
    judge = partial(
        _driven_figures,
        folds,
        records,
        level,
        workers=workers,
        tell=tell,
        rectified=rectified,
        saturating=None if rectified else _sensor_limits(records),
    )
    spreads = np.array([_spread(fold.check) for fold in folds])
    smallest = partial(_smallest_driven, margin=margin, max_order=max_order, samples=samples, spreads=spreads)
    figures, admissible = judge([(n, d, False) for n, d in orders])
    n, d, constant = _with_constant(judge, smallest, orders, figures, smallest(figures, admissible))
    return (n, n, d), linear_terms(n, n, d, constant=constant)


def _with_constant(
    judge: Callable[[list[_Linear]], tuple[dict[_Linear, _Judged], set[_Linear]]],
    smallest: Callable[[dict[_Linear, _Judged], set[_Linear]], _Linear],
    orders: list[tuple[int, int]],
    figures: dict[_Linear, _Judged],
    chosen: _Linear,
) -> _Linear:
    """The start ``chosen`` without a constant, or the orders chosen with one.

    An output at an operating point away from zero, its input about zero, is reached by an ARX
    without a constant only through poles near one: a model that integrates its own past, or one
    of needlessly high order. The orders chosen without a constant are judged with one too; where
    it lowers their figure beyond the spread, every order is judged with a constant as well and
    chosen among as :func:`choose_linear` chooses, the constant counted as one parameter more; of
    the two starts so chosen, the one with the constant is taken where it simulates better beyond
    the margin and the spread, or as well and is smaller. On records about zero the constant
    takes nothing off, and the start stays as it was without the second set of fits."""
    n, d, _ = chosen
    constant, constant_admissible = judge([(n, d, True)])
    if not _lower_beyond_spread(constant[(n, d, True)].figure, figures[chosen].figure):
        return chosen
    more, more_admissible = judge([(m, e, True) for m, e in orders if (m, e) != (n, d)])
    constant |= more
    with_constant = smallest(constant, constant_admissible | more_admissible)
    pair = {key: figures[key] if key == chosen else constant[key] for key in (chosen, with_constant)}
    return smallest(pair, set(pair))


def _sensor_limits(records: Records) -> Saturating | None:
    """The sensor's limits where the records' output plateaus at its range ends
    (:func:`models.effects.output_limits`): every candidate is then judged as a clipping sensor's
    model (:mod:`models.narx`), fitted on the equations clear of the plateaus and run free from
    readings clear of them, its output clipped. A linear model's free run scored against clipped
    readings, from a clipped start, is off by the clipping whatever its order: over a quarter of
    clipped readings every order of the rig ran free alike and a higher one was the start,
    leaving the loop no room for the rig's cubic spring."""
    limits = records_output_limits(records)
    return None if limits is None else (limits, "sensor")


# A linear candidate of :func:`choose_linear`: its order n, input delay d, and whether it has a
# constant.
_Linear = tuple[int, int, bool]


class _Judged(NamedTuple):
    """A linear candidate's held-out free-run RMS on each rotation (:func:`_rotation_figures`),
    its instrumental-variable fit's alone (infinite where that diverged), and whether the input
    drives it (:func:`_driven_figures`)."""

    figure: np.ndarray
    instrumental: np.ndarray
    driven: bool = True


def _linear_figures(
    folds: Sequence[CheckSplit],
    candidates: Sequence[_Linear],
    workers: Workers,
    tell: Stage,
    rectified: bool = False,
    saturating: Saturating | None = None,
) -> tuple[dict[_Linear, _Judged], set[_Linear]]:
    """Each linear candidate's figures on the rotations of ``folds`` (:func:`_rotation_figures`);
    and those that may start the loop (:func:`choose_linear`). ``tell`` is told each candidate as
    its figures are read; ``workers`` judge them."""
    structures = [
        Structure(linear_terms(n, n, d, constant), saturating=saturating, rectified=rectified)
        for n, d, constant in candidates
    ]
    parts = [(fold.fit, fold.check) for fold in folds]
    judged = workers(partial(_rotation_figures, parts), structures)
    figures: dict[_Linear, _Judged] = {}
    admissible: set[_Linear] = set()
    for candidate, (figure, model) in zip(candidates, judged, strict=True):
        n, d, constant = candidate
        tell(f"linear orders: ARX({n}, {n}){' with a constant' if constant else ''}, input delay {d}")
        figures[candidate] = figure
        if model is not None and _is_start(model, folds[0]):
            admissible.add(candidate)
    return figures, admissible


def _driven_figures(
    folds: Sequence[CheckSplit],
    records: Records,
    level: float,
    candidates: Sequence[_Linear],
    workers: Workers,
    tell: Stage,
    rectified: bool = False,
    saturating: Saturating | None = None,
) -> tuple[dict[_Linear, _Judged], set[_Linear]]:
    """:func:`_linear_figures`, each candidate's figures marked with whether the input drives it
    at its delay (:func:`models.input_drive.input_drives` at ``level`` on all the ``records``,
    and with a delay of 0 :func:`models.input_drive.feeds_through`: a model with x[t] whose
    coefficient is nil holds the delay-1 model of its order and a parameter more, and on the rig,
    whose force reaches the output at x[t-4], ARX(5, 5) with x[t] ran free over the three
    rotations of a short record a little better than ARX(4, 4) by chance). A rectified model's
    linear terms read the recursion under the fold, which a linear fit of the readings does not:
    there every candidate counts as driven, judged by its free run alone."""
    figures, admissible = _linear_figures(folds, candidates, workers, tell, rectified, saturating)
    if not rectified:
        for n, d, constant in candidates:
            terms = linear_terms(n, n, d, constant)
            driven = input_drives(records, terms, level) and (d > 0 or feeds_through(records, terms, level))
            figures[n, d, constant] = figures[n, d, constant]._replace(driven=driven)
    return figures, admissible


def _rotation_figures(
    parts: Sequence[tuple[Segments, Segments]], structure: Structure
) -> tuple[_Judged, NARX | None]:
    """``structure`` fitted on the fit parts of each rotation's ``parts`` (fit, check) by
    instrumental variables (:meth:`CheckSplit.instrumental`) and by output error, and run free
    over its check parts: the better fit's figure and the instrumental-variable fit's; and the
    better fit on the first rotation (None where neither can be made).

    Least squares' estimate is biased wherever its equation error is not white (an unmeasured
    force, noise on the output, a nonlinearity the linear model lacks), and a larger order then
    runs free better by modelling that error: on a linear rig of fourth order under an unmeasured
    force, least squares' ARX(8, 8) ran free below ARX(4, 4) over all three rotations. Both
    estimates here are consistent. The instrumental-variable one has no unique value beyond the
    system's order, so that such an order does not run free better, and it is what a smaller order
    is kept by (:func:`_smallest_near_best`); output error, searched a few steps from measured
    starts, placed slow poles on the rig that ran off over its check blocks, but where it settles
    it simulates best (Silverbox's ARX(2, 2): 8.6 mV by output error, 9.5 by instrumental
    variables), and where the instrumental-variable estimate is unstable it is the one there is
    (the DC motor/generator's ARX(3, 3) with a constant, fitted on the blocks after its spin-up
    from rest)."""
    figure, instrumental, models = [], [], []
    for fit, check in parts:
        checks = CheckSplit(fit, check)
        # A rectified model's instruments would be its folded readings: output error alone.
        model, error = (None, np.inf) if structure.rectified else checks.instrumental(structure)
        instrumental.append(error)
        tuned = checks.error(structure, tuned=True)
        if tuned < error:
            model, error = checks.tuned(structure), tuned
        figure.append(error)
        models.append(model)
    return _Judged(np.array(figure), np.array(instrumental)), models[0]


def _lower_beyond_spread(figure: np.ndarray, other: np.ndarray) -> bool:
    """Whether ``figure`` is below ``other`` on average by more than the standard error of their
    difference across the rotations; a ``figure`` finite on every rotation is below an ``other``
    that diverged on one (:func:`_smallest_driven` may start from such a candidate)."""
    if not np.all(np.isfinite(figure)):
        return False
    if not np.all(np.isfinite(other)):
        return True
    difference = other - figure
    return float(np.mean(difference)) > float(np.std(difference, ddof=1) / np.sqrt(difference.size))


def _smallest_driven(
    figures: dict[_Linear, _Judged],
    admissible: set[_Linear],
    margin: float,
    max_order: int,
    samples: int,
    spreads: np.ndarray,
) -> _Linear:
    """:func:`_smallest_near_best` among the admissible candidates the input drives (their input
    coefficients significant, :func:`_driven_figures`): on the rig's records with a sensor that
    clips, or a quadratic spring, every linear model runs free poorly and ARX(2, 2), whose input
    lags stop short of the rig's x[t-4] and whose input coefficients are nil, ran free as well as
    ARX(4, 4) and was the start. With nothing of the input's to find, the loop, whose families
    are sized to the start's lags, cannot reach the effect the linear models lack, and an output
    extrapolated from its own past can run free better than any linear model driven through a
    strong nonlinearity (on 3200 samples of the rig with a sensor clipping nearly half of them,
    ARX(2, 2) ran free below ARX(4, 4) on all three rotations, where the loop from ARX(4, 4) names
    the saturation first). So a candidate the input does not drive is taken only where it drives
    none.

    Among those it drives, the choice is by their free runs where some run free over every
    rotation: below the check parts' ``spreads`` (the RMS of the measured output about its mean
    on each rotation), since a free run no closer than the output's mean has not simulated it,
    whether it diverged or stayed finite over a short block. Where none does (on a short record
    of the rig with a strong quadratic spring, every order the input drives diverged on one
    rotation, and ARX(9, 9), finite there, ran free at a hundred times the output's spread on
    another), the free runs cannot tell their orders apart, and the smallest the input drives
    is taken (of those fitted and run free without diverging on one rotation at least): the order
    that reaches the input's delay."""
    chosen = _smallest_near_best(figures, admissible, margin, max_order, samples, spreads)
    pool = admissible or set(figures)
    driven = {key for key in pool if figures[key].driven and np.any(np.isfinite(figures[key].figure))}
    if figures[chosen].driven or not driven:
        return chosen
    running = {key for key in driven if _simulates(figures[key].figure, spreads)}
    if not running:
        return min(driven, key=lambda key: (_parameters(key), key[0]))
    return _smallest_near_best(
        {key: figures[key] for key in running}, running, margin, max_order, samples, spreads
    )


def _simulates(figure: np.ndarray, spreads: np.ndarray) -> bool:
    """Whether a candidate's free-run ``figure`` is below the output's ``spreads`` on every
    rotation: closer than a model that answers the output's mean (:func:`_spread`)."""
    return bool(np.all(figure < spreads))


def _spread(check: Segments) -> float:
    """The RMS of the measured output about its mean over the ``check`` parts: the free-run RMS
    of a model that answers the output's mean whatever the input."""
    y = np.concatenate([y for _, y, _ in check])
    return float(np.sqrt(np.mean((y - np.mean(y)) ** 2)))


def _smallest_near_best(
    figures: dict[_Linear, _Judged],
    admissible: set[_Linear],
    margin: float,
    max_order: int,
    samples: int,
    spreads: np.ndarray,
) -> _Linear:
    """The smallest admissible candidate near the best (:func:`choose_linear`): its mean figure,
    raised for its size on the ``samples`` held out (:func:`_size_penalty`), within ``margin`` of
    the best's so raised; or its figures above the best's by no more than the spread of their
    difference (a question of noise, which the size does not enter); or its instrumental-variable
    fit running free no worse than the best on one rotation at least. A larger order is taken only
    where it simulates better on every rotation, as a family is added across folds. The smaller
    order's own figure there is its instrumental-variable fit's: an output-error search from
    measured starts on short blocks can end well on one rotation by chance (on the rig, ARX(3, 3)
    with x[t], which cannot hold the input's delay of four samples, ran free over one rotation
    below ARX(4, 4)).

    None is near a best that runs free over every rotation closer than the output's mean (below
    the check parts' ``spreads``) unless it does too: a free run off by many times the output's
    spread on one rotation widens the spread of the difference, and on the rig with power-law
    damping ARX(7, 7), finite there at sixty times the output's spread, passed as near the best
    by it and by its instrumental-variable fit's chance on another rotation."""
    # Where the input drives none (an output the input reaches through a strong nonlinearity), the
    # best of all is the start: the loop may still find what the input does.
    mean = {
        key: float(np.mean(judged.figure)) * _size_penalty(_parameters(key), samples)
        for key, judged in figures.items()
        if key in admissible or not admissible
    }
    best = min(mean, key=mean.__getitem__)
    if not np.isfinite(mean[best]):
        raise InputError(
            f"no linear model of order 1 to {max_order} could be fitted on these records and run free "
            "over their held-out parts without diverging"
        )
    lowest = figures[best].figure
    simulates = _simulates(lowest, spreads)

    def near_best(key: _Linear) -> bool:
        if simulates and not _simulates(figures[key].figure, spreads):
            return False
        return (
            mean[key] <= (1 + margin) * mean[best]
            or not _lower_beyond_spread(lowest, figures[key].figure)
            or not bool(np.all(lowest < figures[key].instrumental))
        )

    # The smallest by parameters, then by order.
    return min(
        (key for key in mean if np.isfinite(mean[key]) and near_best(key)),
        key=lambda key: (_parameters(key), key[0]),
    )


def rectified_orders(
    records: Records, checks: CheckSplit | None, tell: Stage, workers: Workers
) -> tuple[Term, ...] | None:
    """Where the records' outputs read as a magnitude (:func:`models.effects.reads_magnitude`),
    the linear terms :func:`choose_linear` picks for the rectified model, which the rectified
    family starts from in the first round (:func:`models.round_criteria.rectified_first`); None
    elsewhere. A sensor blind to the sign folds the output at zero, and a linear model of the
    readings fits the folds with other orders than the recursion under the fold wants (the coupled
    drives: (1, 1) and (2, 2) for the readings, three lags under the rectifier)."""
    if not reads_magnitude(np.concatenate([y for _, y in records])):
        return None
    return choose_linear(records, checks=checks, progress=tell, workers=workers, rectified=True)[1]


def _parameters(candidate: _Linear) -> int:
    """The parameters of a linear candidate of :func:`choose_linear`: x[t] is one more than a
    delay of one, the constant one more."""
    n, delay, constant = candidate
    return 2 * n + (delay == 0) + constant


def _size_penalty(parameters: int, samples: int) -> float:
    """The factor by which :func:`choose_linear` raises a linear candidate's held-out free-run
    RMS for its ``parameters``: the Bayesian information criterion's ``ln(samples)`` per
    parameter on the ``samples`` the rotations hold out between them, N·ln(RMS²) + k·ln(N), as a
    factor on the RMS. A few hundred samples give three check rotations too few to tell a few
    parameters more from chance, and a larger model always fits some of them a little better;
    on records of tens of thousands of samples the factor is near one and the spread decides."""
    return float(np.exp(parameters * np.log(samples) / (2 * samples)))


def _is_start(model: NARX, checks: CheckSplit) -> bool:
    """Whether ``model`` (fitted on the fit parts) may start the loop: over the check parts its
    response to the input alone (run from rest) is at least ``INPUT_SHARE`` of the measured
    output's spread about its mean."""
    lag = model.max_lag
    driven, spread = [], []
    for x, y, t0 in checks.check:
        if len(y) > lag:
            # Less the response to no input: a constant's alone is the operating point, no drive.
            resting = model.simulate(np.zeros_like(x), np.zeros_like(y), t0)[lag:]
            driven.append(model.simulate(x, np.zeros_like(y), t0)[lag:] - resting)
            spread.append(y[lag:] - np.mean(y[lag:]))
    if not spread:
        return False
    response, scale = (float(np.sqrt(np.mean(np.concatenate(s) ** 2))) for s in (driven, spread))
    return bool(np.isfinite(response)) and response >= INPUT_SHARE * scale
