"""The check split (SPEC §7): a model structure fitted on part of the estimation data and judged
by its free run over the rest.

:func:`split_for_checking` cuts the records into fit and check parts (blocks of one or two
records; from three records on, whole records, in three folds); :class:`CheckSplit` fits a
:class:`Structure` on the fit parts, by least squares or by output error (bounded or settled),
and keeps the check parts' free-run RMS of every structure it judged. A model that does not come
to rest once the excitation stops, or diverges from a measured state of the fit parts, counts as
diverged.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from models.errors import InputError
from models.instrumental import fit_instrumental
from models.narx import NARX, run_start, sensor_limits
from models.output_error import comes_to_rest, fit_output_error
from models.regression import Workers
from models.scoring import Records, Saturating, fit_model
from models.simulation import FreeRun
from models.terms import OUTPUT_HYSTERESES, Term, max_lag

# With fewer than three records each is cut into 3·CHECK_BLOCKS blocks, every third one a check
# block, so that fit and check parts cover the record alike (a growing amplitude, say). A sine
# sweep's blocks hold different frequencies, though: from three records on, whole records are
# checked instead.
CHECK_BLOCKS = 3
MIN_BLOCK = 200  # samples of the shortest block; shorter records get fewer blocks
# Output-error searches within the loop are bounded; a settled one runs until it stops gaining
# (MINPACK's tolerances), within this bound: the final one on all the data, and those that judge a
# family across folds. On F-16's sweeps the linear (10, 10, 1) model of acceleration 2 cut at 30
# evaluations runs free over the check sweep at 0.535 m/s², settled (about 130) at 0.326, and any
# family searched longer than the model it is compared with "gains" by the extra evaluations alone.
CHECK_EVALUATIONS = 30
SETTLED_EVALUATIONS = 400

Segment = tuple[np.ndarray, np.ndarray, int]  # (x, y, first sample's index in its record)
Segments = list[Segment]
Limits = tuple[float, float]
# The functions of a term whose value depends on the whole past of their signal: a Bouc–Wen
# variable of the output, a backlash's play on the input (a dead zone is memoryless).
MEMORIES = (*OUTPUT_HYSTERESES, "backlash")


@dataclass(frozen=True)
class Structure:
    """A model structure as the loop grows it: terms, moving-average order, output saturation,
    and whether its sensor reads a magnitude."""

    terms: tuple[Term, ...]
    noise_lags: int = 0
    saturating: Saturating | None = None
    rectified: bool = False


# What a split made for a structure judged in a split of its own (in a worker): the least-squares
# and output-error fits, the check figures, and the figures judged against a bound only
# (:meth:`CheckSplit.judge`'s ``matters``).
Figures = dict[tuple[Structure, bool], float]
Found = tuple[dict[Structure, NARX], dict[Structure, NARX], Figures, Figures]
# Whether a check figure would change what the caller decides; false of every larger figure.
Matters = Callable[[float], bool]


@dataclass
class CheckSplit:
    """The estimation data's fit and check parts (:func:`split_for_checking`), and the check
    parts' free-run RMS of every structure judged on them, kept with its fits: the loop asks
    again for the current model's (each round, the final choice of estimator), and an
    output-error search starts from the least-squares fit the judgement made."""

    fit: Segments
    check: Segments
    _errors: dict[tuple[Structure, bool], float] = field(default_factory=dict)
    _fitted: dict[Structure, NARX] = field(default_factory=dict)
    _tuned: dict[Structure, NARX] = field(default_factory=dict)
    _settled: set[Structure] = field(default_factory=set)
    _beyond: Figures = field(default_factory=dict)
    # Judgements sent to the workers ahead of being asked for (:meth:`judge_ahead`), each with
    # the iterator its result comes from.
    _ahead: dict[tuple[Structure, bool], Iterator[Found]] = field(default_factory=dict)

    @classmethod
    def of(cls, records: Records, fold: int = 1) -> CheckSplit:
        return cls(*split_for_checking(records, fold))

    def error(self, structure: Structure, tuned: bool = False) -> float:
        """Free-run RMS over the check parts of ``structure`` fitted on the fit parts (its
        parameters by output error if ``tuned``); each run starts from its part's first measured
        outputs. Infinite when the fit is impossible or a run diverges."""
        key = (structure, tuned)
        self._collect(key)
        if key not in self._errors:
            self._errors[key] = self._judge(structure, tuned)
        return self._errors[key]

    def judge_ahead(self, structures: Sequence[Structure], workers: Workers, tuned: bool = False) -> None:
        """Send ``structures`` not judged yet to the ``workers`` now, each to be judged in a split
        of its own as :meth:`judge` judges it, and go on: :meth:`error`, :meth:`judge` and
        :meth:`tuned` read a judgement sent ahead where they would make it. With a process pool
        they are made while this process does other work; with the builtin map, when first read."""
        unjudged = [
            s
            for s in dict.fromkeys(structures)
            if (s, tuned) not in self._errors and (s, tuned) not in self._ahead
        ]
        judged = iter(
            workers(
                partial(_judged, self.fit, self.check, tuned, None),
                [(s, self._fitted.get(s)) for s in unjudged],
            )
        )
        for structure in unjudged:
            self._ahead[(structure, tuned)] = judged

    def _collect(self, key: tuple[Structure, bool]) -> None:
        """Keep the judgement of ``key`` sent ahead (:meth:`judge_ahead`), and those sent before it
        with it, waiting for it where it is not made yet."""
        judged = self._ahead.get(key)
        while key in self._ahead and judged is not None:
            found = next(judged)
            self._keep(found)
            for made in found[2]:
                self._ahead.pop(made, None)

    def judge(
        self,
        structures: Sequence[Structure],
        workers: Workers = map,
        tuned: bool = False,
        matters: Matters | None = None,
    ) -> Iterator[float]:
        """:meth:`error` of each of ``structures`` in turn, lazily; those not judged yet are
        judged by ``workers`` (:data:`models.regression.Workers`), each in a split of its own with
        these parts, and what they fitted kept here: the figures are the same whichever.

        With ``matters``, a structure whose free run over the check parts gives a figure that
        does not matter is not asked whether it comes to rest (the ring-downs over the fit parts,
        a quarter of a judgement): its figure is that run's RMS, a bound below :meth:`error`'s
        (which is that or infinite) that gives ``matters`` the same answer. Only :meth:`error`'s
        own figures are kept as such."""
        for structure in structures:
            self._collect((structure, tuned))
        unjudged = [s for s in dict.fromkeys(structures) if self._figure(s, tuned, matters) is None]
        # Each with the least-squares fit made here, where one was: an output-error search
        # starts from it, and a worker would make it again (extended least squares on Silverbox's
        # 51 terms: a third of a second before the search).
        judged = workers(
            partial(_judged, self.fit, self.check, tuned, matters),
            [(s, self._fitted.get(s)) for s in unjudged],
        )
        for structure in structures:
            if self._figure(structure, tuned, matters) is None:
                for found in judged:
                    self._keep(found)
                    if self._figure(structure, tuned, matters) is not None:
                        break
            figure = self._figure(structure, tuned, matters)
            assert figure is not None
            yield figure

    def _figure(self, structure: Structure, tuned: bool, matters: Matters | None) -> float | None:
        """The check figure :meth:`judge` gives, where one was found: :meth:`error`'s, or with
        ``matters`` a bound that does not matter."""
        key = (structure, tuned)
        if key in self._errors:
            return self._errors[key]
        beyond = self._beyond.get(key)
        return beyond if matters is not None and beyond is not None and not matters(beyond) else None

    def search_grown(
        self, current: Structure, structures: Sequence[Structure], evaluations: int, workers: Workers = map
    ) -> Iterator[float]:
        """:meth:`search` of each of ``structures`` (grown from ``current``) from :meth:`grown`, for
        at most ``evaluations``, in turn and lazily, the searches made by ``workers`` as
        :meth:`judge` makes its judgements."""
        start = self.tuned(current)
        searched = workers(partial(_searched, self.fit, self.check, current, start, evaluations), structures)
        for structure, found in zip(structures, searched, strict=True):
            self._keep(found)
            yield self._errors[(structure, True)]

    def _keep(self, found: Found) -> None:
        """What a split of its own made for a structure (:func:`_judged`, :func:`_searched`)."""
        fitted, tuned, errors, beyond = found
        self._fitted |= fitted
        self._tuned |= tuned
        self._errors |= errors
        self._beyond |= beyond

    def tuned(self, structure: Structure) -> NARX:
        """``structure`` fitted on the fit parts by output error (as :meth:`error` judges it with
        ``tuned``); the least-squares fit where output error gains nothing."""
        self._collect((structure, True))
        if structure not in self._tuned:
            self._tuned[structure] = by_output_error(self.fitted(structure), self.fit, CHECK_EVALUATIONS)
        return self._tuned[structure]

    def search(self, structure: Structure, start: NARX | None, evaluations: int) -> float:
        """Search ``structure``'s parameters by output error on the fit parts from ``start`` (a
        model of its terms; None: its least-squares fit), for at most ``evaluations``, and keep
        the result as its output-error fit (:meth:`tuned`). Returns :meth:`error` of it, kept
        as that: infinite, as :meth:`error` judges it, where ``structure`` cannot be fitted here
        (:meth:`search_grown` reads the figure kept)."""
        self._collect((structure, True))
        try:
            start = self.fitted(structure) if start is None else start
        except InputError:
            self._errors[(structure, True)] = np.inf
            return np.inf
        self._tuned[structure] = by_output_error(start, self.fit, evaluations)
        self._errors[(structure, True)] = self._simulates(self._tuned[structure])
        return self._errors[(structure, True)]

    def grown(self, current: Structure, structure: Structure) -> NARX | None:
        """``structure`` with ``current``'s output-error fit on the fit parts and zero on the terms
        it adds, which simulates as that fit does; None (start from least squares) when
        ``structure`` cannot be fitted here."""
        try:
            return grown_by_zeros(self.tuned(current), self.fitted(structure))
        except InputError:
            return None

    def settled(self, structure: Structure, start: NARX | None = None) -> float:
        """:meth:`error` of ``structure``'s output-error fit searched until it stops gaining
        (:meth:`search` to ``SETTLED_EVALUATIONS``), once."""
        if structure not in self._settled:
            self.search(structure, start, SETTLED_EVALUATIONS)
            self._settled.add(structure)
        return self.error(structure, tuned=True)

    def instrumental(self, structure: Structure) -> tuple[NARX | None, float]:
        """``structure`` fitted on the fit parts by instrumental variables from its least-squares
        fit (:func:`models.instrumental.fit_instrumental`), and its free-run RMS over the check
        parts as :meth:`error` judges a fit; None and infinite where it cannot be made."""
        try:
            model = fit_instrumental(self.fitted(structure), self.fit)
        except InputError:
            return None, np.inf
        return model, np.inf if model is None else self._simulates(model)

    def _judge(self, structure: Structure, tuned: bool, matters: Matters | None = None) -> float:
        # A rectified structure's least-squares fit is its recursion's on the readings, blind to
        # the fold: it is judged by its output-error fit whichever is asked for.
        try:
            model = self.tuned(structure) if tuned or structure.rectified else self.fitted(structure)
        except InputError:
            return np.inf
        if matters is None:
            return self._simulates(model)
        rms = free_run_rms(model, self.check)
        if not matters(rms):
            self._beyond[(structure, tuned)] = rms
            return rms
        return self._simulates(model, rms)

    def _simulates(self, model: NARX, rms: float | None = None) -> float:
        """The check parts' free-run RMS of ``model`` (``rms`` where that run was made), or
        infinite. A model that does not come to rest once the excitation stops, or diverges from
        a measured state, is as good as diverged, however well it simulates from the parts'
        starts."""
        if not comes_to_rest(model, [(x, y) for x, y, _ in self.fit], [t for *_, t in self.fit]):
            return np.inf
        return free_run_rms(model, self.check) if rms is None else rms

    def fitted(self, structure: Structure) -> NARX:
        """``structure`` fitted on the fit parts by least squares (its process part by extended
        least squares when it has moving-average terms); raises InputError where it cannot be."""
        if structure not in self._fitted:
            self._fitted[structure], _ = fit_model(
                [(x, y) for x, y, _ in self.fit],
                structure.terms,
                structure.noise_lags,
                max_lag(structure.terms),
                [t for *_, t in self.fit],
                structure.saturating,
                structure.rectified,
            )
        return self._fitted[structure]


def _judged(
    fit: Segments, check: Segments, tuned: bool, matters: Matters | None, job: tuple[Structure, NARX | None]
) -> Found:
    """What :meth:`CheckSplit.judge` of a structure fits and finds on these parts, ``job`` being
    the structure and its least-squares fit there if one was made: the least-squares and
    output-error fits, and the figures."""
    structure, fitted = job
    checks = CheckSplit(fit, check, _fitted={} if fitted is None else {structure: fitted})
    figure = checks._judge(structure, tuned, matters)
    if (structure, tuned) not in checks._beyond:
        checks._errors[(structure, tuned)] = figure
    return checks._fitted, checks._tuned, checks._errors, checks._beyond


def _searched(
    fit: Segments, check: Segments, current: Structure, tuned: NARX, evaluations: int, structure: Structure
) -> Found:
    """What :meth:`CheckSplit.search` of ``structure`` from :meth:`CheckSplit.grown` of
    ``current`` (whose output-error fit is ``tuned``) fits and finds on these parts."""
    checks = CheckSplit(fit, check, _tuned={current: tuned})
    checks.search(structure, checks.grown(current, structure), evaluations)
    del checks._tuned[current]
    return checks._fitted, checks._tuned, checks._errors, checks._beyond


def by_output_error(model: NARX, segments: Segments, evaluations: int, threads: Workers = map) -> NARX:
    """``model`` with its parameters refined by output error on ``segments`` when that lowers
    its free-run error there; ``model`` itself when its free run diverges or nothing is gained.
    ``threads`` as for :func:`models.output_error.fit_output_error`."""
    try:
        records = [(x, y) for x, y, _ in segments]
        fit = fit_output_error(model, records, evaluations, t0=[t for *_, t in segments], threads=threads)
    except InputError:
        return model
    return fit.model if fit.rms < fit.start_rms else model


def clears(bar: float, figure: float) -> bool:
    """Whether a check ``figure`` is at or below ``bar``: what matters (:data:`Matters`) to a
    caller that takes only such figures, as a partial of it, which the workers can be sent."""
    return figure <= bar


def check_noise(check: Segments) -> float:
    """The standard error of a free-run RMS over the ``check`` parts, as a share of it: 1/√(2N)
    for N independent Gaussian errors (fewer independent ones only widen it)."""
    return float(1 / np.sqrt(2 * sum(len(y) for _, y, _ in check)))


def split_for_checking(records: Records, fold: int = 1) -> tuple[Segments, Segments]:
    """The estimation data split into the parts a candidate is fitted on and the check parts its
    free run is judged on, each part with its first sample's index in its record.

    Three records or more: every third record (the second, fifth, … for ``fold`` 1; the first,
    fourth, … for 0; the third, sixth, … for 2) is checked whole and the others are fitted, a
    split across experiments alike in design (a sweep or multisine at several levels, say).
    Fewer: each record is cut into 3·k equal blocks (k = ``CHECK_BLOCKS``, fewer for short
    records); for ``fold`` 1 blocks 3i and 3i+1 are fitted, block 3i+2 is checked (for 0, block
    3i; for 2, block 3i+1), contiguous fitted blocks fitted as one part.
    """
    if len(records) >= 3:
        return (
            [(x, y, 0) for index, (x, y) in enumerate(records) if index % 3 != fold],
            [(x, y, 0) for x, y in checked_whole(records, fold)],
        )
    fit: Segments = []
    check: Segments = []
    for x, y in records:
        n = len(y)
        blocks = int(np.clip(n // (3 * MIN_BLOCK), 1, CHECK_BLOCKS))
        edges = np.linspace(0, n, 3 * blocks + 1).astype(int)
        checked = (fold + 1) % 3
        runs: list[tuple[int, int]] = []  # the fitted stretches, contiguous blocks joined
        for i in range(3 * blocks):
            a, b = int(edges[i]), int(edges[i + 1])
            if i % 3 == checked:
                check.append((x[a:b], y[a:b], a))
            elif runs and runs[-1][1] == a:
                runs[-1] = (runs[-1][0], b)
            else:
                runs.append((a, b))
        fit += [(x[a:b], y[a:b], a) for a, b in runs]
    return fit, check


def checked_whole(records: Records, fold: int = 1) -> Records:
    """The records the check parts come from (:func:`split_for_checking`): from three records on
    every third one, from the one ``fold`` counts from 0; fewer, all (a part of each)."""
    return list(records[fold::3]) if len(records) >= 3 else list(records)


def free_run_rms(model: NARX, segments: Segments, pasts: Records | None = None) -> float:
    """Free-run RMS of ``model`` over ``segments``, each run started from its first measured
    outputs (a sensor-saturating model's from its first clear of the limits; its memory from
    ``pasts``, :func:`free_run_errors`); infinite when a run diverges or
    no segment is longer than the model's lags."""
    return pooled_rms(free_run_errors(model, segments, pasts))


def free_run_errors(
    model: NARX, segments: Segments, pasts: Records | None = None, limits: Limits | None = None
) -> list[np.ndarray]:
    """The free-run errors of ``model`` over each of ``segments`` longer than its lags, each run
    started from its first measured outputs (samples L … of each, L the model's largest lag).

    ``pasts``, where given, holds each segment's record before it (its input and output as
    measured, ending where the segment starts). A model with memory — a Bouc–Wen variable of the
    output, the play of a backlash on the input — then runs that memory over them, as its lags
    read the segment's first measured outputs: its state at the segment's start is what the
    measurements make it, where started at rest there it would be wrong by up to the memory's
    whole level, and stay wrong until the signal has moved by that much (over a held-out tail of
    a few hundred samples, perhaps never).

    A sensor-saturating model's run starts where its first L readings lie clear of the sensor's
    limits (``limits``, by default its own; :func:`models.narx.run_start`), its memory run over
    the samples passed over; ``limits`` given, every model's run starts so, that two models
    compared over the same segments are scored on the same samples."""
    L = model.max_lag
    errors = []
    for index, segment in enumerate(segments):
        if len(segment[1]) <= L:
            continue
        past = pasts[index] if pasts is not None else None
        (x, y, t0), past = started_clear(segment, past, L, sensor_limits(model) if limits is None else limits)
        past = past if remembers(model.terms) else None
        if past is None or not len(past[1]):
            errors.append(model.run_free(FreeRun.build(model.terms, x, t0), y)[L:] - y[L:])
            continue
        before = len(past[1])
        x_all, y_all = np.concatenate((past[0], x)), np.concatenate((past[1], y))
        run = FreeRun.build(model.terms, x_all, t0 - before).measured_to(before + L)
        errors.append(model.run_free(run, y_all)[before + L :] - y[L:])
    return errors


def started_clear(
    segment: Segment, past: tuple[np.ndarray, np.ndarray] | None, lag: int, limits: Limits | None
) -> tuple[Segment, tuple[np.ndarray, np.ndarray] | None]:
    """``segment`` from where a free run of ``lag`` lags starts on it clear of a sensor's
    ``limits`` (:func:`models.narx.run_start`), the samples passed over joined to its ``past``
    (where one is given), which a model's memory runs over as over the rest of its past."""
    x, y, t0 = segment
    skip = run_start(y, lag, limits) - lag
    if not skip:
        return segment, past
    if past is not None:
        past = (np.concatenate((past[0], x[:skip])), np.concatenate((past[1], y[:skip])))
    return (x[skip:], y[skip:], t0 + skip), past


def remembers(terms: Sequence[Term]) -> bool:
    """Whether ``terms`` hold a memory of the signals' past beyond their lags: a Bouc–Wen
    variable of the output or a backlash's play on the input."""
    return any(f.function in MEMORIES for term in terms for f in term.factors)


def pooled_rms(errors: Sequence[np.ndarray]) -> float:
    """The RMS of all the ``errors`` together; infinite when one is not finite or there are none."""
    squares, count = 0.0, 0
    for error in errors:
        squares += float(error @ error)
        count += error.size
    rms = np.sqrt(squares / count) if count else np.inf
    return float(rms) if np.isfinite(rms) else np.inf


def grown_by_zeros(model: NARX, structure: NARX) -> NARX:
    """``structure`` (grown from ``model``'s terms) with ``model``'s parameters on the terms they
    share and zero on the others."""
    theta = dict(zip((term.name for term in model.terms), model.theta, strict=True))
    return replace(structure, theta=np.array([theta.get(term.name, 0.0) for term in structure.terms]))
