"""Closing the loop (SPEC §7): residual → the effect the model lacks → refined model.

Starting from a declared structure (or, with none declared, from a linear model whose orders the
loop chooses), each round

1. fits the current model on the estimation records and takes its one-step residual e (a NARX
   by least squares; once moving-average noise terms are in, a NARMAX by extended least squares);
2. scores every named candidate effect by how much of e it explains (:mod:`models.scoring`:
   partial F tests at a Bonferroni level, ranked by the fall of the Bayesian information
   criterion);
3. checks the significant effects, best first, on the **simulation error**: the model with the
   effect is fitted on part of the estimation data and run free over the rest (the check
   blocks, each free run started from its first measured outputs). The first effect that lowers
   that free run by more than its standard error (:func:`models.checking.check_noise`; moving-average noise,
   which is there to unbias the parameters, need only not make it worse) is added — decided by
   the one-step criterion — unless a later one lowers it by a further ``SIMULATION_GAIN`` of the
   current figure and, each added and the next round judged, ends lower (:func:`_looked_ahead`).
   Where none clears, a family whose least-squares model diverges there is judged by output
   error, grown from the current model's output-error fit (:func:`_by_output_error_grown`);
4. if no effect is significant on e (on slow, finely sampled data the one-step residual carries
   little of the simulation error), or every significant one made the free run worse, each
   family's regressors are tried in the order of their error reduction, and the family whose
   model (parameters refined by output error, as is the current model's) lowers the check
   blocks' free-run RMS by at least ``SIMULATION_GAIN`` is added — decided by the simulation
   criterion. Where none does, the first significant family is judged with the family the
   round after it adds (:func:`_paired`): two effects can each run free worse alone and far
   better together. Otherwise the loop stops.

After the rounds, the loop prunes back (Piroddi & Spinelli 2003): a term the rounds added goes
where the check blocks' free run without it is no higher than the figure the rounds ended at
(:func:`_pruned`), judged as the model will be fitted: where output error
simulates better, by its output-error fit as well. The generic polynomial is tried whole where a
later effect may have made it redundant; then the terms not significant in the least-squares fit,
together, else by halves; then one at a time, those the fit needs least (smallest t statistic)
first. The pruning never takes a named effect's last term. Each round reports the candidates it
compared on the check blocks' free run, and the fall of that free run the effect added brought
(else the best judged) against the fall it had to reach; the last, what the pruning took out,
and a round whose generic block went whole says so.

The generic polynomial (:func:`models.effects.polynomial_effect`, products of two of the model's
lags, no physical effect named) is scored with the named families but judged after them: steps 3
and 4 run for the named families first, and only where neither adds one for the polynomial.

After the rounds, the refined structure must simulate the check blocks better than the declared
one, both with their parameters by output error (from three records on, on every fold below);
otherwise what the rounds added is withdrawn and the declared structure kept.

**Across folds.** From three records on, the structure kept is then grown on the simulation error
across folds: each third of the records in turn is checked and the rest fitted. Every family's
terms are added at zero to the current model's output-error fit; the best families on the first
fold are searched until they stop gaining on every fold, and of those whose free run over the
checked records falls by ``FOLD_GAIN`` on all three, the one that falls most on average is added
— decided by the simulation across folds. This repeats until no family passes. (On F-16's sweeps
the rounds above add nothing that lasts: least squares ranks the families there, and every
cubic-stiffness model it fits diverges; grown from the settled linear model, cubic stiffness
gains 8–29 % on every fold.)

**Never worse.** The rounds choose among many candidates on the same check blocks, and the best
of many gains there by chance: where the records are long enough, the loop runs on each record's
first part only, and the model it refines is compared with its start on the records' tails,
which no choice saw (:mod:`models.held_out`). Unless it simulates them better beyond the
comparison's uncertainty, the start is returned and the report says the data could not support
the effects, naming the best one tried. Whichever is returned has its parameters estimated on
all the records as the loop estimated them on its part (:func:`refine`).

**Settling.** A record often starts with the machine, before it has settled (a motor warming up
from rest). Where the structure returned is fitted by least squares, it is fitted again on the
heads without their first eighth, quarter, three eighths and half; where one of those fits runs
free over the tails better than the fit on the whole heads, beyond the comparison's uncertainty
at the held-out level split among the four, and predicts them one step ahead better, the model
is estimated from where the records settled and the report says what was left out
(:func:`_settled_from`). That is one more choice the tails
make, after the comparison with the start, and at a stricter level.

The refined structure's parameters are finally refined by output-error minimisation on all the
estimation records (:func:`models.output_error.fit_output_error`), which removes the bias that
noise on the measured output gives least squares, when on the check blocks the output-error fit
simulates better than the least-squares one (where the noise is a force on the structure, least
squares is consistent and the better one-step predictor, and may simulate as well). When
nothing was added, the refined model is the declared structure's output-error fit itself; when
families were added across folds, it is made as each fold made the model it judged (the folds
validate that procedure), their terms grown at zero from the fit before them.

The estimation data may be several records: no lag crosses a record boundary; from three
records on, whole records are checked (:mod:`models.checking`). Free runs are compiled
(:mod:`models.simulation`).

Where the checked records repeat their excitation, the spread between periods gives the noise no
model can simulate (:mod:`models.periods`). Reported beside the check blocks' free run, it says how
much of that figure any model could still take off: on the Wiener–Hammerstein records, whose
process noise is 86 mV RMS, the linear model's figure is within half a per cent of it.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from itertools import compress, islice, pairwise
from typing import Any, Literal, NamedTuple, get_args

import numpy as np

from models.assessment import Assessment, assess, check_test_length
from models.checking import (
    CHECK_EVALUATIONS,
    MIN_BLOCK,
    SETTLED_EVALUATIONS,
    CheckSplit,
    Matters,
    Segments,
    Structure,
    by_output_error,
    check_noise,
    checked_whole,
    free_run_rms,
    grown_by_zeros,
)
from models.coverage import Coverage, coverage
from models.effects import (
    POLYNOMIAL,
    RECTIFIED,
    Effect,
    candidate_effects,
    linear_terms,
    offset_terms,
    output_limits,
    reads_magnitude,
    unused,
)
from models.errors import InputError
from models.held_out import HELD_OUT_ALPHA, HeldOut, compare_on_tails, held_out_tails, unseen_by
from models.input_drive import input_drives
from models.narx import NARX, Saturation, z_quantile
from models.output_error import comes_to_rest, free_run_at_rest
from models.periods import PeriodNoise, excitation_period, pooled_period_noise
from models.regression import Workers
from models.scoring import EffectScore, Records, Scores, ScoringKept, fit_model, score_effects
from models.signals import GLITCH_FACTOR, checked_records, glitches
from models.terms import WAVES, Term, max_degree, max_lag, parse_terms

DEFAULT_ALPHA = 0.01
MAX_ROUNDS = 10
# Told each stage of the loop as it begins, in words ("round 2: scoring 17 families"): a loop on
# long records runs for minutes, and a caller shows where it is.
Stage = Callable[[str], None]
# A family added on the simulation error alone must lower the check blocks' free-run RMS by this
# share at least: SEMP's threshold (Piroddi & Spinelli 2003), here relative. Where an unmeasured
# force drives much of the output, the free run over a few thousand check samples is a noisy
# figure: on clean records of the 2-DOF rig (800 N disturbance) families of no effect lowered it
# by up to 8 % by chance; the effects the one-step residual misses (a plateau, a drain) take far
# more off it.
SIMULATION_GAIN = 0.2
# From three records on, a family is added on the simulation error across folds (module
# docstring) when its settled model lowers the checked records' free run by this share on every
# fold; the best FOLD_TRIALS families of the first fold, by bounded searches, are tried on all.
FOLD_GAIN = 0.05
FOLD_TRIALS = 3
MAX_LINEAR_ORDER = 10  # the largest order tried when no structure is declared
# A larger linear start is chosen only when it simulates the held-out data better than a smaller
# by this share and by more than their difference's spread across the check rotations
# (:func:`choose_linear`).
ORDER_GAIN = 0.05
# A linear start's response to the input alone must reach this share of the output's spread.
INPUT_SHARE = 0.1
# Families judged at once on the check blocks, in a round (the workers' judgements run side by
# side): of Silverbox's ten rounds from linear:4,4, four add the first family judged, and the
# others the second to the fourth.
JUDGED_AT_ONCE = 2
# Removals of one term the pruning judges on the free run at once, the smallest t statistics,
# once the batches of terms not significant are refused (:func:`_pruned`): the workers' fits run
# side by side, and where the first is refused the next may pass.
PRUNING_TRIALS = 2
# Once a family clears the one-step criterion's margin, this many more in the one-step order are
# judged on the check blocks for a larger gain (:func:`_looked_ahead`).
CONTENDERS = 4
# The first parts of the estimation records' heads tried as stretches where the system had not
# settled (:func:`_settled_from`), as shares of each head: at most half, so that most of what the
# loop chose on stays.
SETTLING_SHARES = (0.125, 0.25, 0.375, 0.5)
# Glitches a report names by their sample; more are counted.
GLITCHES_NAMED = 5

Criterion = Literal[
    "one-step", "output error", "simulation", "simulation across folds", "output's range", "pair"
]
Estimator = Literal["least squares", "output error"]
Verdict = Literal["better", "not better", "diverged"]


@dataclass(frozen=True)
class Round:
    """One round of the loop: every effect's score, the level used, and the effect added (if any).

    ``criterion`` says what decided the effect added: "one-step" (its regressors were significant
    on the one-step residual and its model's free run over the check blocks lower by more than its
    standard error), "output error" (significant so, its least-squares model diverging there,
    and its model grown from the current one's output-error fit lowering that free run by more
    than its standard error), "simulation" (it lowered that free run by at least
    ``SIMULATION_GAIN``), "simulation across folds" (its settled output-error model lowered the
    free run over the checked records of each of three folds by at least ``FOLD_GAIN``),
    "output's range" (the rectifier, taken where the records read as a magnitude) or "pair" (the
    first significant family, whose model alone ran free worse, with the family the next round
    adds lowering that free run by at least ``SIMULATION_GAIN``: :func:`_paired`);
    ``check_rms`` is the check blocks' free-run RMS before and after the round (by output error,
    settled, across folds).
    """

    residual_rms: float
    level: float  # the Bonferroni-corrected significance level α / M
    candidates: int  # M
    scores: tuple[EffectScore, ...]
    added: EffectScore | None
    criterion: Criterion | None = None
    check_rms: tuple[float, float] = (np.inf, np.inf)
    # Significant effects passed over, best first, because adding them did not lower the model's
    # free run over the check blocks by the round's threshold (or made it diverge).
    rejected: tuple[str, ...] = ()
    # The terms pruned after the rounds, in the order taken out (:func:`_pruned`), on the last
    # round; ``check_rms`` is then after the pruning.
    pruned: tuple[str, ...] = ()
    # The effect added here (the generic polynomial) pruned whole after the rounds: a later
    # round's effect made it redundant, and the refined model holds none of its terms.
    pruned_whole: bool = False
    # The candidates whose free run over the check blocks the round compared with the model's
    # (each significant family judged on it, each structure simulated for a family's terms), and
    # the fall of that free-run RMS the effect added brought (else the best judged), with the
    # fall it had to reach, both shares of the RMS before; NaN where none was judged.
    tried: int = 0
    gain: float = np.nan
    threshold: float = np.nan


@dataclass(frozen=True)
class Refinement:
    """The declared and refined models and the rounds that led from one to the other.

    ``declared`` is the declared structure fitted by least squares on all the estimation data;
    ``refined`` the refined structure, its parameters by ``estimator``. ``noise`` holds the
    refined model's moving-average coefficients c_1 … c_q (empty unless moving-average noise was
    added; ``refined`` is then the process part of a NARMAX). ``orders`` are the linear model's
    (ny, nx, input delay) the loop chose when no structure was declared. ``withdrawn``: the final
    check took back every effect the first ``withdrawn`` rounds added (module docstring); the
    rounds after them were decided across folds. ``check_rms`` is the refined structure's
    free-run RMS over the check blocks, its parameters by ``estimator`` fitted on the fit blocks;
    ``noise_floor`` the noise between the checked records' periods when they repeat their
    excitation (None otherwise): the least any model's free run over them can leave.
    ``held_out`` is the comparison of the refined model with the start on the tails of the
    records that no choice saw (:mod:`models.held_out`); None where nothing was added or the
    records are too short to hold a tail out. Where the start won, every round counts as
    withdrawn.
    """

    declared: NARX
    refined: NARX
    noise: np.ndarray = field(default_factory=lambda: np.empty(0))
    rounds: tuple[Round, ...] = field(default=())
    estimator: Estimator = "least squares"
    orders: tuple[int, int, int] | None = None
    withdrawn: int = 0
    check_rms: float = np.inf
    noise_floor: PeriodNoise | None = None
    held_out: HeldOut | None = None
    # The samples left out at the start of each estimation record, where the system had not
    # settled (:func:`_settled_from`); empty where none were.
    settled_from: tuple[int, ...] = ()

    @property
    def kept(self) -> tuple[Round, ...]:
        """The rounds whose effect the refined model holds."""
        return tuple(r for r in self.rounds[self.withdrawn :] if r.added is not None and not r.pruned_whole)

    @property
    def effects_added(self) -> tuple[EffectScore, ...]:
        return tuple(r.added for r in self.kept if r.added is not None)

    @property
    def effects_withdrawn(self) -> tuple[str, ...]:
        """The names of the effects the final check or the held-out comparison took back, each
        once (moving-average noise is often added over several rounds)."""
        return tuple(
            dict.fromkeys(r.added.name for r in self.rounds[: self.withdrawn] if r.added is not None)
        )


@dataclass(frozen=True)
class Comparison:
    """The declared and the refined model judged on one held-out record (or part), and how much
    of it lies outside the estimation data (:func:`models.coverage.coverage`)."""

    before: Assessment
    after: Assessment
    coverage: Coverage

    @property
    def verdict(self) -> Verdict:
        """The refined model's free run here beside the declared one's: "diverged" where it
        diverged, "better" where its RMS is lower (or the declared one's diverged), else "not
        better"."""
        if self.after.diverged:
            return "diverged"
        if self.before.diverged or self.after.free_run_rms < self.before.free_run_rms:
            return "better"
        return "not better"


@dataclass(frozen=True)
class RefinementReport:
    """A refinement with the declared and refined models' errors on held-out data: ``tests``
    holds one comparison a test record; ``before``/``after`` are the first one's."""

    refinement: Refinement
    tests: tuple[Comparison, ...]
    notes: tuple[str, ...] = ()

    @property
    def before(self) -> Assessment:
        return self.tests[0].before

    @property
    def after(self) -> Assessment:
        return self.tests[0].after

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: effects added in order with their evidence and the criterion that
        decided each, errors before and after on every test record, and both models' terms and
        parameters. Non-finite numbers (a diverged free run) become None."""
        result = self.refinement
        return {
            "declared": _model_dict(result.declared),
            "orders_chosen": list(result.orders) if result.orders else None,
            "effects_added": [
                {
                    "name": score.name,
                    "description": score.description,
                    "terms": list(score.terms),
                    "decided_by": step.criterion,
                    "evidence": {
                        "explained_fraction": score.explained,
                        "bic_change": score.bic_change,
                        "residual_rms_before": step.residual_rms,
                        "f_statistics": list(score.f_statistics),
                        "p_values": list(score.p_values),
                        "level": step.level,
                        "candidate_terms": step.candidates,
                        "check_free_run_rms": [_finite(value) for value in step.check_rms],
                    }
                    | _selection_dict(step),
                }
                for step in result.kept
                if (score := step.added) is not None
            ],
            "effects_withdrawn": list(result.effects_withdrawn),
            "rounds": [
                {"round": number, "added": None if step.added is None else step.added.name}
                | _selection_dict(step)
                | {
                    "decided_by": step.criterion,
                    "check_free_run_rms": [_finite(v) for v in step.check_rms],
                    "pruned_whole": step.pruned_whole,
                }
                for number, step in enumerate(result.rounds, start=1)
            ],
            "held_out": None if result.held_out is None else _held_out_dict(result.held_out),
            "check_free_run_rms": _finite(result.check_rms),
            "noise_floor": None
            if (floor := result.noise_floor) is None
            else _floor_dict(floor, result.check_rms),
            "before": self.before.to_dict(),
            "after": self.after.to_dict(),
            "tests": [
                {
                    "before": test.before.to_dict(),
                    "after": test.after.to_dict(),
                    "coverage": asdict(test.coverage)
                    | {"extrapolates": test.coverage.extrapolates, "description": test.coverage.describe()},
                    "verdict": test.verdict,
                }
                for test in self.tests
            ],
            "refined": _model_dict(result.refined)
            | {"noise_ma": result.noise.tolist(), "estimator": result.estimator},
            "settled_from": list(result.settled_from),
            "notes": list(self.notes)
            + _held_out_notes(result)
            + _settled_notes(result)
            + _skipped_notes(self.tests),
        }


def _selection_dict(step: Round) -> dict[str, Any]:
    """How a round chose: the candidates it compared on the check blocks' free run, the fall of
    that free run it saw and the fall needed (shares of it; None where none was judged), and the
    terms pruned after its addition."""
    return {
        "candidates_tried": step.tried,
        "threshold": _finite(step.threshold),
        "gain": _finite(step.gain),
        "pruned": list(step.pruned),
    }


def _held_out_dict(held_out: HeldOut) -> dict[str, Any]:
    """The comparison on the held-out tails: both free runs, the refined model's gain and the
    threshold its uncertainty set (shares of the start's mean square), and the decision."""
    return {
        "samples": held_out.samples,
        "start_free_run_rms": _finite(held_out.start_rms),
        "refined_free_run_rms": _finite(held_out.refined_rms),
        "gain": _finite(held_out.gain),
        "threshold": _finite(held_out.threshold),
        "level": HELD_OUT_ALPHA,
        "diverged": held_out.diverged,
        "refined_returned": held_out.kept,
        "best_tried": held_out.best_tried,
        "orders_saw_tails": held_out.orders_saw_tails,
    }


def _held_out_notes(result: Refinement) -> list[str]:
    """What the report says where the effects added could not be compared with the start on data
    no choice saw, or were and lost."""
    held_out = result.held_out
    if held_out is None:
        if not result.effects_added:
            return []
        return [
            "the estimation records are too short to hold a tail out (a fifth of each, and two "
            "whole periods of a periodic input before it): the effects added were not compared "
            "with the start on data no choice of the loop saw"
        ]
    if held_out.kept:
        return []
    refined = "diverged" if held_out.diverged else f"ran free at {held_out.refined_rms:.4g}"
    return [
        f"the data could not support the effects: over the estimation records' held-out tails "
        f"({held_out.samples} samples {unseen_by(held_out.orders_saw_tails)}) the refined model "
        f"{refined} against the start's "
        f"{held_out.start_rms:.4g}, not better beyond the comparison's uncertainty; the start is "
        f"returned (the best effect tried: {held_out.best_tried})"
    ]


def _skipped_notes(tests: Sequence[Comparison]) -> list[str]:
    """A note for each test record too short for the residual tests, naming those skipped."""
    return [
        f"test record {number} is too short for the residual tests ({', '.join(test.after.skipped)}): "
        "skipped; its free-run and one-step errors are scored"
        for number, test in enumerate(tests, start=1)
        if test.after.skipped
    ]


def refine_record(
    x: np.ndarray,
    y: np.ndarray,
    declared: Sequence[str | Term] | None,
    estimation: Sequence[tuple[int, int]],
    test: tuple[int, int],
    initial: int = 0,
    alpha: float = DEFAULT_ALPHA,
    fs: float | None = None,
    output_error: bool = True,
    progress: Stage | None = None,
    workers: Workers = map,
    threads: Workers = map,
) -> RefinementReport:
    """Refine on the ``estimation`` parts (a, b) of one record, assess both models on ``test``.

    Several parts are fitted as records of their own, no lag reaching from one to the next, so
    that what lies between them (a glitch) is left out. The first ``initial`` test samples only
    start the predictions (benchmark protocols prescribe such a start, e.g. 50 samples for
    Silverbox). ``output_error``, ``progress``, ``workers`` and ``threads`` as for :func:`refine`.
    """
    check_parts(len(x), declared, estimation, test, initial)
    c, d = test
    estimation_part = [(x[a:b], y[a:b]) for a, b in estimation]
    result = refine(
        estimation_part,
        declared,
        alpha=alpha,
        output_error=output_error,
        progress=progress,
        workers=workers,
        threads=threads,
    )
    _told(progress)("judging both models on the test part")
    t0 = c - estimation[0][0]  # the test part's time from the first part's start
    comparison = compare(result, estimation_part, x[c:d], y[c:d], initial, fs, t0)
    notes = _notes(len(estimation)) + _glitch_notes(
        estimation_part,
        lambda signal, part, index: f"{signal}[{estimation[part][0] + index}]",
        "leave it out with estimation parts around it",
    )
    return RefinementReport(result, (comparison,), notes)


def refine_records(
    estimation: Records,
    tests: Records,
    declared: Sequence[str | Term] | None,
    initial: int = 0,
    alpha: float = DEFAULT_ALPHA,
    fs: float | None = None,
    transient: int = 0,
    progress: Stage | None = None,
    workers: Workers = map,
    threads: Workers = map,
    names: Sequence[str] | None = None,
) -> RefinementReport:
    """Refine on several estimation records, assess both models on each test record, whole.

    Each test run starts from its record's first ``initial`` measured outputs (at least the
    model's lags); its first ``transient`` samples are run through but not scored
    (:func:`models.assessment.assess`). A model with sinusoidal terms is phase-locked to the
    estimation record's first sample; on a test record its sinusoids count time from that
    record's first sample. ``progress``, ``workers`` and ``threads`` as for :func:`refine`;
    ``names`` are how the notes call the estimation records (a file, a stored record's id;
    by default "record k", k from 1, where there are several).
    """
    if not tests:
        raise InputError("at least one test record is needed to judge the refined model")
    if initial < 0 or transient < 0:
        raise InputError(f"the initial and transient samples must be 0 or more, got {initial}, {transient}")
    for number, (_, y) in enumerate(tests, start=1):
        try:
            check_test_length(len(y), max(initial, reach(declared), transient))
        except InputError as exc:
            raise InputError(f"test record {number}: {exc}") from None
    result = refine(estimation, declared, alpha=alpha, progress=progress, workers=workers, threads=threads)
    tell, comparisons = _told(progress), []
    for number, (x, y) in enumerate(tests, start=1):
        tell(f"judging both models on test record {number} of {len(tests)}")
        comparisons.append(compare(result, estimation, x, y, initial, fs, 0, transient))
    if names is None and len(estimation) > 1:
        names = [f"record {number}" for number in range(1, len(estimation) + 1)]
    notes = _notes(len(estimation)) + _glitch_notes(
        estimation,
        lambda signal, record, index: f"{signal}[{index}]" + (f" of {names[record]}" if names else ""),
        "cut it out of its record",
    )
    if _of_time(result.refined.terms):
        notes += (
            "the refined model's periodic terms keep the phase of the estimation record's first "
            "sample; the test records share no time base with it, so those terms are not validated there",
        )
    return RefinementReport(result, tuple(comparisons), notes)


def _notes(stretches: int) -> tuple[str, ...]:
    """What the report says of a loop on ``stretches`` records, or parts of one."""
    if stretches == 1:
        return ()
    return (
        "periodic disturbances were not looked for: a sinusoid of time is fitted on one stretch of "
        "samples, and the estimation data are several",
    )


def _glitch_notes(records: Records, label: Callable[[str, int, int], str], cure: str) -> tuple[str, ...]:
    """A note for each signal, x and y, naming its glitches in the estimation ``records``
    (:func:`models.signals.glitches`, over all of them together), each by ``label(signal, record's
    number from 0, sample within it)``; ``cure`` says how the caller leaves a glitch out."""
    notes = []
    ends = np.cumsum([len(y) for _, y in records])
    for signal, what, column in (("x", "input", 0), ("y", "output", 1)):
        everything = np.concatenate([record[column] for record in records])
        found = glitches(everything)
        if not found.size:
            continue
        named = []
        for index in found[:GLITCHES_NAMED]:
            part = int(np.searchsorted(ends, index, side="right"))
            where = label(signal, part, int(index - (ends[part - 1] if part else 0)))
            named.append(f"{where} = {everything[index]:.4g}")
        more = f" and {found.size - GLITCHES_NAMED} more samples" if found.size > GLITCHES_NAMED else ""
        verb = "lies" if found.size == 1 else "lie"
        notes.append(
            f"{', '.join(named)}{more} {verb} more than {GLITCH_FACTOR:g} times as far from the estimation "
            f"data's median {what} as 99 % of its samples do, as a glitch does; least squares weighs such "
            f"a sample as hundreds of others: if it is one, {cure}"
        )
    return tuple(notes)


def _of_time(terms: Sequence[Term]) -> bool:
    """Whether any of ``terms`` holds a sinusoid of time."""
    return any(factor.signal in WAVES for term in terms for factor in term.factors)


def compare(
    result: Refinement,
    estimation: Records,
    x: np.ndarray,
    y: np.ndarray,
    initial: int,
    fs: float | None,
    t0: int,
    transient: int = 0,
) -> Comparison:
    """Both of ``result``'s models, declared and refined, assessed on (x, y)
    (:func:`models.assessment.assess`), and how much of its scored samples lies outside the
    ``estimation`` records the models were fitted on (:func:`models.coverage.coverage`)."""
    return Comparison(
        assess(result.declared, x, y, initial, fs, t0, transient=transient),
        assess(result.refined, x, y, initial, fs, t0, result.noise, transient=transient),
        coverage(estimation, x[transient:], y[transient:]),
    )


def check_parts(
    n: int,
    declared: Sequence[str | Term] | None,
    estimation: Sequence[tuple[int, int]],
    test: tuple[int, int],
    initial: int = 0,
) -> None:
    """Refuse estimation and test parts that do not fit a record of ``n`` samples, estimation
    parts that overlap or are out of order, a sinusoid of time declared with several (each part
    would count its time, and the sinusoid's phase, from its own start), or a test part too short
    to judge the models on: checked before the loop, which takes far longer."""
    if not estimation:
        raise InputError("give at least one estimation part")
    for label, (first, last) in [*(("estimation", part) for part in estimation), ("test", test)]:
        if not 0 <= first < last <= n:
            raise InputError(f"the {label} samples {first}:{last} do not lie within the record's {n} samples")
    for (a, b), (c, d) in pairwise(estimation):
        if c < b:
            raise InputError(
                f"the estimation parts must follow one another without overlapping: {c}:{d} starts "
                f"before {a}:{b} ends"
            )
    if len(estimation) > 1 and declared and _of_time(parse_terms(declared)):
        raise InputError(
            "a declared sinusoid of time is fitted on one stretch of samples: give one estimation part"
        )
    if initial < 0:
        raise InputError(f"the initial samples must be 0 or more, got {initial}")
    check_test_length(test[1] - test[0], max(initial, reach(declared)))


def reach(declared: Sequence[str | Term] | None) -> int:
    """The most samples any model the loop may reach from ``declared`` looks back: the declared
    lags and every candidate effect's (a linear start of the largest order when none is
    declared). A test record must hold this many before the residual tests' samples."""
    terms = parse_terms(declared) if declared else linear_terms(MAX_LINEAR_ORDER, MAX_LINEAR_ORDER, 0)
    return max([max_lag(terms)] + [max_lag(e.terms) for e in candidate_effects(terms) if e.terms])


def _model_dict(model: NARX) -> dict[str, Any]:
    limits = model.output_limits
    return {
        "terms": model.term_names,
        "theta": model.theta.tolist(),
        # The limits a saturating model clips to (None: none), and whether a state or a sensor does.
        "output_limits": None if limits is None else [_finite(v) for v in limits],
        "saturation": None if limits is None else model.saturation,
        # Whether the sensor reads the magnitude of the recursion's output (models.narx).
        "rectified": model.rectified,
    }


def _floor_dict(floor: PeriodNoise, check_rms: float) -> dict[str, Any]:
    """The noise floor, its standard error, and the part of the check blocks' free run above it."""
    return asdict(floor) | {
        "standard_error": floor.standard_error,
        "check_model_error": _finite(floor.beneath(check_rms)),
    }


def _told(progress: Stage | None) -> Stage:
    """``progress``, or a stage that tells no one."""
    return progress if progress is not None else lambda stage: None


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None


def refine(
    records: Records,
    declared: Sequence[str | Term] | None,
    effects: Sequence[Effect] | None = None,
    alpha: float = DEFAULT_ALPHA,
    max_rounds: int = MAX_ROUNDS,
    output_error: bool = True,
    progress: Stage | None = None,
    workers: Workers = map,
    threads: Workers = map,
) -> Refinement:
    """Refine the declared structure on the estimation ``records`` (x, y pairs) until no effect
    helps (module docstring).

    ``declared`` None starts from the linear model :func:`choose_linear` picks. ``effects`` are
    the families on offer, by default :func:`models.effects.candidate_effects` of the declared
    terms: sized to the declared lags, so that the loop explains the residual with the declared
    dynamics rather than by lengthening them round after round. An offset's terms follow the
    model as it grows. ``output_error`` False keeps least-squares parameters throughout.
    ``progress`` is told each stage as it begins. ``workers`` run the loop's independent pieces
    (:data:`models.regression.Workers`): each round's searched candidates, the structures judged on
    the check parts, the output-error searches not needed one after the other; ``threads``, a map
    over threads of this process, test each round's families (:func:`score_effects`). The
    refinement is the same whichever.

    **Never worse.** Where every record is long enough (:func:`models.held_out.held_out_tails`),
    the last ``HELD_OUT_SHARE`` of each is held out from every choice (orders, effects, estimator):
    the loop runs on the rest, and the model it refines is kept only where its free run over
    those tails is better than the start's beyond the comparison's uncertainty
    (:func:`models.held_out.compare_on_tails`; moving-average noise alone, which leaves the
    process structure as it was, need only not be worse). Otherwise the start is returned, every
    round counted as withdrawn, and ``held_out`` names the best effect tried. The structure so
    judged then has its parameters estimated on all the records as the loop estimated them on
    the rest (:func:`_on_all`): the tails judged a procedure, and the model it makes gains from
    every sample.

    **Short records.** Tails shorter than ``MIN_BLOCK`` (records of a few hundred samples, down to
    ``models.held_out.MIN_TAIL``) are held out as well, with two differences. The linear start is
    chosen on the whole records, not the heads: a fifth fewer of a few hundred samples moves the
    orders (the coupled drives' PRBS record at ±1: (10, 10, 0) on its first 320 samples, running
    free over the test at 1.24 ticks/s, against (1, 1, 1) and 0.66 on all 400), and the tails'
    part in that choice can only favour the start, the side the comparison errs to. The start is
    fitted by output error only where that runs free over the tails no worse than least squares
    (:func:`_start_on_tails`). And moving-average noise alone must simulate the tails better, like
    any effect: over three blocks the comparison's uncertainty is a large share of the mean
    square, and "no worse beyond it" kept noise terms that took the drives' test free run from
    0.662 to 0.677 ticks/s.
    """
    tell = _told(progress)
    if not 0 < alpha < 1:
        raise InputError(f"alpha must lie in (0, 1), got {alpha}")
    records = [(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)) for x, y in records]
    grow = partial(
        _grown,
        declared=declared,
        effects=effects,
        alpha=alpha,
        max_rounds=max_rounds,
        output_error=output_error,
        tell=tell,
        workers=workers,
        threads=threads,
    )
    split = held_out_tails(records)
    if split is None:
        return grow(records).refinement
    heads, tails = split
    short = any(len(y) < MIN_BLOCK for _, y, _ in tails)
    orders_saw_tails = short and declared is None
    if orders_saw_tails:
        orders, terms = choose_linear(records, progress=tell, workers=workers)
        rectified = _rectified_orders(records, None, tell, workers)
        grow = partial(grow, declared=terms, orders=orders, rectified=rectified)
    try:
        grown = grow(heads)
    except InputError:
        # Too few equations for the candidates once the tails are held out: refined on all of
        # them, with nothing to compare on (the report says so).
        return grow(records).refinement
    if short:
        grown = _start_on_tails(grown, heads, tails)
    result, held_out = grown.refinement, None
    if result.effects_added:
        tell("the refined model and the start on the held-out tails")
        held_out = replace(
            compare_on_tails(grown.start, result.refined, tails), orders_saw_tails=orders_saw_tails
        )
        refined, start = result.refined, grown.start
        # Moving-average noise alone, there to unbias the parameters, leaves the process
        # structure as it was: on long tails it need only not make the free run worse.
        noise_only = refined.terms == start.terms and refined.output_limits == start.output_limits
        if not (held_out.better or (noise_only and not short and held_out.not_worse)):
            held_out = replace(held_out, kept=False, best_tried=_best_tried(result.kept))
    settled = _settled_from(grown, held_out, heads, tails, tell)
    if not any(settled):
        return _on_all(grown, held_out, records, output_error, tell, threads)
    settled_records = [(x[cut:], y[cut:]) for (x, y), cut in zip(records, settled, strict=True)]
    return replace(
        _on_all(grown, held_out, settled_records, output_error, tell, threads), settled_from=settled
    )


def _settled_from(
    grown: _Grown, held_out: HeldOut | None, heads: Records, tails: Segments, tell: Stage
) -> tuple[int, ...]:
    """Where each estimation record's settled part begins: 0 for each, unless the structure
    :func:`_on_all` will return, fitted by least squares on the ``heads`` without a first share of
    each (``SETTLING_SHARES``), runs free over the held-out ``tails`` better than fitted on the
    whole heads beyond the comparison's uncertainty (at ``HELD_OUT_ALPHA`` split among the shares
    tried) and predicts them one step ahead better too; then where the share that gained most
    begins. A machine that changed is predicted better one step ahead as well; the free run over a
    short tail alone can favour a fit on fewer samples by chance where a lightly damped model's
    slow error drifts through every block of the comparison (the rig's records).

    A record often starts with the machine: a motor switched on from rest warms up, its friction
    and windings' resistance drifting for minutes before they settle, and a least-squares fit
    over the whole record averages the machine it became with the one it was (the DC
    motor/generator's record, which starts at rest). The tails, the record's latest samples, tell
    which. Where the structure is fitted by output error a search per share would cost as much
    as the final fit; where it holds a sinusoid of time, cutting a record moves its phase: neither
    is tried.
    """
    result = grown.refinement
    kept = bool(result.effects_added) and (held_out is None or held_out.kept)
    structure = grown.structure if kept else Structure(result.declared.terms)
    estimator = result.estimator if kept else grown.start_estimator
    settled = (0,) * len(heads)
    if estimator != "least squares" or _of_time(structure.terms):
        return settled
    tell("the estimation records without their first parts, on the held-out tails")
    whole, _ = _fitted_on_all(heads, structure)
    periods = [excitation_period(x) for x, _ in heads]
    best = 0.0
    for share in SETTLING_SHARES:
        # Whole periods of an input that repeats, as the heads are cut (:mod:`models.held_out`).
        cuts = tuple(
            int(len(y) * share) - (int(len(y) * share) % period if period else 0)
            for (_, y), period in zip(heads, periods, strict=True)
        )
        try:
            model, _ = _fitted_on_all(
                [(x[c:], y[c:]) for (x, y), c in zip(heads, cuts, strict=True)], structure
            )
        except InputError:  # too few equations left for the structure
            continue
        judged = compare_on_tails(whole, model, tails, HELD_OUT_ALPHA / len(SETTLING_SHARES))
        predicts = _one_step_square(model, tails) < _one_step_square(whole, tails)
        if any(cuts) and judged.better and predicts and judged.gain > best:
            settled, best = cuts, judged.gain
    return settled


def _one_step_square(model: NARX, segments: Segments) -> float:
    """``model``'s mean square one-step prediction error over the ``segments``."""
    errors = np.concatenate([model.residuals(x, y, t0) for x, y, t0 in segments])
    return float(np.mean(errors**2))


def _settled_notes(result: Refinement) -> list[str]:
    """What the report says where the first samples of the estimation records were left out."""
    if not any(result.settled_from):
        return []
    left_out = ", ".join(str(cut) for cut in result.settled_from)
    records = "record was" if len(result.settled_from) == 1 else "records were"
    return [
        f"the first {left_out} samples of the estimation {records} left out: fitted without them "
        "the model ran free over the held-out tails better, beyond the comparison's uncertainty, "
        "and predicted them better one step ahead, as where a system has not yet settled (a "
        "machine warming up from rest)"
    ]


def _start_on_tails(grown: _Grown, heads: Records, tails: Segments) -> _Grown:
    """``grown`` with its start by least squares where the loop chose output error for it on the
    ``heads``' check blocks and its free run over the short ``tails`` is worse than least
    squares': on a few hundred samples that choice rests on a free run over a hundred, and the
    tails judge it as they judge the effects (the coupled drives' PRBS records: output error
    chosen on 320 samples ran free over the test 3–6 % worse than least squares)."""
    if grown.start_estimator != "output error":
        return grown
    least_squares = grown.refinement.declared
    if free_run_rms(grown.start, tails) <= free_run_rms(least_squares, tails):
        return grown
    check = CheckSplit.of(heads).error(Structure(least_squares.terms))
    return grown._replace(start=least_squares, start_estimator="least squares", start_check=check)


class _Grown(NamedTuple):
    """What the loop made of its records: the refinement; the start as the loop fits it when it
    adds nothing (the declared structure, its parameters by ``start_estimator``) with its check
    blocks' free-run RMS; the structure refined; and, where families were grown across folds, the
    structure before them and each grown (:func:`_as_the_folds_judged`)."""

    refinement: Refinement
    start: NARX
    start_estimator: Estimator
    start_check: float
    structure: Structure
    folded: tuple[Structure, tuple[Structure, ...]] | None


def _on_all(
    grown: _Grown,
    held_out: HeldOut | None,
    records: Records,
    output_error: bool,
    tell: Stage,
    threads: Workers,
) -> Refinement:
    """The refinement the loop ``grown`` on the records' heads made, its models' parameters
    estimated again on all the ``records``, tails too, as the loop estimated them: the refined
    structure where ``held_out`` kept it, else the start. The declared model by least squares;
    the start by its estimator (its output-error fit searched from least squares, as where nothing
    is added); a structure grown across folds as the folds judged it; any other refined structure
    by output error from the best simulating of its least-squares fit, the parameters the loop
    found and the start's grown by zeros. An output-error fit is kept where it comes to rest. The
    noise floor is read on the whole records, whose periods a tail cut off leaves incomplete."""
    result = grown.refinement
    declared_structure = Structure(result.declared.terms)
    declared, _ = _fitted_on_all(records, declared_structure)
    everything: Segments = [(x, y, 0) for x, y in records]
    kept = bool(result.effects_added) and (held_out is None or held_out.kept)
    structure = grown.structure if kept else declared_structure
    estimator = result.estimator if kept else grown.start_estimator
    refined, noise = _fitted_on_all(records, structure) if kept else (declared, np.empty(0))
    if estimator == "output error":
        tell("output-error fit on all the records")
        declared_tuned = None
        if not kept or (grown.folded is not None and grown.folded[0] == declared_structure):
            declared_tuned = by_output_error(declared, everything, SETTLED_EVALUATIONS, threads)
        if not kept:
            tuned = declared_tuned
        elif grown.folded is not None:
            before, structures = grown.folded
            tuned = _as_the_folds_judged(
                records, before, structures, declared_structure, declared_tuned or declared, threads
            )
        else:
            starts = [refined, replace(refined, theta=result.refined.theta)]
            if grown.start_estimator == "output error":
                starts.append(grown_by_zeros(grown.start, refined))
            start = min(starts, key=lambda model: _restless_then_rms(free_run_at_rest(model, records)))
            tuned = by_output_error(start, everything, SETTLED_EVALUATIONS, threads)
        if tuned is not None and tuned is not refined and comes_to_rest(tuned, records):
            refined = tuned
        else:
            estimator = "least squares"
    return replace(
        result,
        declared=declared,
        refined=refined,
        noise=noise,
        estimator=estimator,
        withdrawn=result.withdrawn if kept or not result.effects_added else len(result.rounds),
        check_rms=result.check_rms if kept else grown.start_check,
        noise_floor=pooled_period_noise(checked_whole(records)),
        held_out=held_out,
    )


def _best_tried(kept: Sequence[Round]) -> str | None:
    """The effect whose round lowered the check blocks' free run most, as a share of it."""
    judged = [step for step in kept if step.added is not None and step.check_rms[0] > 0]
    best = min(judged, key=lambda step: step.check_rms[1] / step.check_rms[0], default=None)
    return None if best is None or best.added is None else best.added.name


def _grown(
    records: Records,
    declared: Sequence[str | Term] | None,
    effects: Sequence[Effect] | None,
    alpha: float,
    max_rounds: int,
    output_error: bool,
    tell: Stage,
    workers: Workers,
    threads: Workers,
    orders: tuple[int, int, int] | None = None,
    rectified: tuple[Term, ...] | None = None,
) -> _Grown:
    """The loop of :func:`refine` on all of ``records``, and what :func:`_on_all` needs to make
    its models again on more. ``orders``: the linear orders ``declared`` was chosen with, and
    ``rectified`` the linear terms chosen as the rectified model's (:func:`_rectified_orders`),
    where the caller chose them (:func:`refine` on short records)."""
    checks = CheckSplit.of(records)
    kept = ScoringKept()  # a model scored again: after a look ahead, by the simulation criteria
    if declared is None:
        orders, terms = choose_linear(records, checks=checks, progress=tell, workers=workers)
        rectified = _rectified_orders(records, checks, tell, workers)
    else:
        terms = parse_terms(declared)
    families = list(effects) if effects is not None else candidate_effects(terms)
    checked_records(records, 1, degree=max(max_degree(terms), 3))
    _check_length(records, terms, families)
    declared_model, _ = fit_model(records, terms, 0, max_lag(terms))
    current = Structure(terms)
    check = checks.error(current)
    margin = check_noise(checks.check)
    rounds: list[Round] = []
    for number in range(1, max_rounds + 1):
        offered = unused([_follow(effect, current.terms) for effect in families], current.terms)
        offered = [e for e in offered if not _offered_again(e, current)]
        if not offered:
            break
        kinds = {effect.name: effect.kind for effect in offered}
        tell(f"round {number}: scoring {len(offered)} {'family' if len(offered) == 1 else 'families'}")
        scores = _scored(records, current, offered, alpha, workers, threads, kept=kept)
        step = Round(scores.residual_rms, scores.level, scores.candidates, scores.scores, None)
        rejected: list[str] = []
        decided: tuple[EffectScore, Criterion, Structure, float] | None = None
        ranked: Scores | None = None
        judged: Gain | None = None  # the effect added's, else the best judged's
        tried = 0
        if output_error and number == 1 and rectified is not None:
            decided = _rectified_first(current, rectified, offered, scores.scores, checks, workers)
            if decided is not None:
                # Taken on the readings' shape: no fall on the check blocks it had to reach.
                tried, judged = 1, Gain(_fall(decided[3], check), -np.inf)
        # The named families on both criteria first, then the generic polynomial on both: where a
        # named effect explains the data, the loop names it.
        tier = [e.name == POLYNOMIAL for e in offered]
        for generic in (False, True) if decided is None else ():
            significant = sorted(
                (s for s, g in zip(scores.scores, tier, strict=True) if s.significant and g == generic),
                key=lambda s: s.bic_change,
            )
            in_turn = _judged_in_turn(
                significant,
                kinds,
                current,
                records,
                checks,
                workers,
                tell,
                f"round {number}",
            )
            for score, error, structure in in_turn:
                tried += 1
                # Moving-average noise, there to unbias the parameters, need only not make it worse.
                gain = Gain(_fall(error, check), 0.0 if structure.noise_lags > current.noise_lags else margin)
                if error <= (1 - gain.threshold) * check:
                    decided, judged = (score, "one-step", structure, error), gain
                    break
                judged = _better(judged, gain)
                rejected.append(score.name)
            if decided is None and output_error:
                decided = _by_output_error_grown(
                    significant, kinds, current, records, check, margin, checks, workers
                )
                rejected = [name for name in rejected if decided is None or name != decided[0].name]
                if decided is not None:
                    judged = Gain(_fall(decided[3], check), margin)
            elif decided is not None:
                ahead = partial(
                    _next_round, records, families, alpha, margin, checks, workers, threads, tell, kept
                )
                first = decided
                decided, contended = _looked_ahead(
                    first, in_turn, current, check, margin, partial(ahead, number + 1)
                )
                tried += contended
                if decided is not first:
                    judged = Gain(_fall(decided[3], check), margin)
            if decided is None and output_error and generic in tier:
                offer = "the generic polynomial" if generic else "the families"
                tell(f"round {number}: {offer} on the simulation error")
                ranked = ranked or _scored(records, current, offered, alpha, workers, threads, True, kept)
                chosen = [g == generic for g in tier]
                decided, simulated, structures = _by_simulation(
                    list(compress(offered, chosen)),
                    list(compress(ranked.scores, chosen)),
                    current,
                    checks,
                    workers,
                )
                tried += structures
                judged = simulated if decided is not None else _better(judged, simulated)
            if decided is None and not generic and number < max_rounds:
                # The partner is an effect of the process: noise, which clears by being no worse,
                # would end the pair where the first left it.
                named = [effect for effect in families if effect.kind != "noise"]
                ahead = partial(
                    _next_round, records, named, alpha, margin, checks, workers, threads, tell, kept
                )
                paired, paired_tried = _paired(
                    significant, kinds, current, records, check, checks, partial(ahead, number + 1)
                )
                tried += paired_tried
                if paired is not None:
                    decided, pair_end = paired
                    rejected = [name for name in rejected if name != decided[0].name]
                    judged = Gain(_fall(pair_end, check), SIMULATION_GAIN)
            if decided is not None:
                break
        if judged is not None:
            step = replace(step, tried=tried, gain=judged.gain, threshold=judged.threshold)
        if decided is None:
            rounds.append(replace(step, rejected=tuple(rejected), check_rms=(check, check)))
            break
        score, criterion, current, error = decided
        step = replace(step, added=score, criterion=criterion, check_rms=(check, error))
        rounds.append(replace(step, rejected=tuple(rejected)))
        check = error
    if current.terms != tuple(terms):
        # Once, after the rounds (:func:`_pruned`); the last round names what went.
        tell("pruning the terms the rounds added")
        current, pruned = _pruned(current, terms, rounds, checks, workers, output_error, alpha)
        if pruned:
            rounds = _without_pruned(rounds, pruned)
            check = checks.error(current)
            rounds[-1] = replace(rounds[-1], check_rms=(rounds[-1].check_rms[0], check))
    declared_structure = Structure(terms)
    folds = [checks] + [CheckSplit.of(records, fold) for fold in (0, 2)] if len(records) >= 3 else []
    # The least-squares fit on all the records of the structure the rounds grew, made by a thread
    # while the workers check that structure by output error below, where this process would
    # wait (a third of a second on Silverbox's NARMAX): unless those checks change the structure,
    # it is the refined model's, or its search's start.
    by_the_rounds, fitted_ahead = current, threads(_call, [partial(_fitted_on_all, records, current)])
    # The declared model's output-error fit on all the records, which the final search may start
    # from, searched by a worker meanwhile, where that search waited for it (0.4 s on Silverbox);
    # with the builtin map, only when asked for. Unused when least squares simulates better.
    everything: Segments = [(x, y, 0) for x, y in records]
    declared_search = workers(
        _call,
        [partial(by_output_error, declared_model, everything, SETTLED_EVALUATIONS)] if output_error else [],
    )
    withdrawn = 0
    if output_error and current != declared_structure:
        tell("the effects added, checked by output error")
        if _repairs_only_bias(declared_structure, current, check, folds or [checks], workers):
            withdrawn = len(rounds)
            current = declared_structure
            check = checks.error(current)
    before_folds, grown_across_folds = current, []
    if output_error and folds:
        for _ in range(max_rounds):
            offered = unused([_follow(effect, current.terms) for effect in families], current.terms)
            scores = _scored(records, current, offered, alpha, workers, threads, True, kept)
            step = Round(
                scores.residual_rms,
                scores.level,
                scores.candidates,
                scores.scores,
                None,
                "simulation across folds",
            )
            found = _across_folds(offered, scores.scores, current, folds, tell, workers)
            if found is None:
                break
            score, current, errors = found
            grown_across_folds.append(current)
            rounds.append(replace(step, added=score, check_rms=errors))
            check = checks.error(current)
    # Least squares is consistent when the noise enters the equation (a force on the structure)
    # and gives the best one-step predictor; output error when the noise is on the measured
    # output. The check blocks tell which simulates better (``check`` is the figure the last
    # family was judged by: output error's where least squares' diverged).
    by_simulation = output_error and (
        current.rectified or checks.error(current, tuned=True) < checks.error(current)
    )
    ((refined, noise),) = fitted_ahead if current == by_the_rounds else [_fitted_on_all(records, current)]
    estimator: Estimator = "least squares"
    declared_tuned: NARX | None = None  # the declared model's output-error fit, once searched
    if by_simulation:
        tell("output-error fit on all the records")
        (declared_tuned,) = declared_search
        if current == declared_structure:
            # Nothing was added: the declared structure's output-error fit, not a second search
            # from other starts, which ends at another optimum of the same structure, better or
            # worse on other records by chance (F-16's acceleration 2 from the linear orders the
            # loop chose: 5–7 % worse than that fit on two test levels).
            tuned = None if declared_tuned is declared_model else declared_tuned
        elif grown_across_folds:
            tuned = _as_the_folds_judged(
                records, before_folds, grown_across_folds, declared_structure, declared_tuned, threads
            )
        else:
            # The search starts from whichever simulates the estimation data best: the
            # least-squares fit; the output-error fit on the fit parts the check just made (near
            # the optimum, so that the search on all the data takes few steps); or the declared
            # model's output-error fit grown by the added terms at zero, which simulates as that
            # model does, so that the search cannot end worse than it, as it can from least
            # squares (F-16's sweeps, Wiener–Hammerstein's records).
            starts = [refined, replace(refined, theta=checks.tuned(current).theta)]
            if declared_tuned is not declared_model:
                starts.append(grown_by_zeros(declared_tuned, refined))
            start = min(starts, key=lambda model: _restless_then_rms(free_run_at_rest(model, records)))
            found = by_output_error(start, everything, SETTLED_EVALUATIONS, threads)
            # The search keeps a start that comes to rest from leaving it; a start that did not
            # (least squares' fit on all the data can differ from the check's) is no better.
            tuned = None if found is start else found
        if tuned is not None and comes_to_rest(tuned, records):
            refined, estimator = tuned, "output error"
    refinement = Refinement(
        declared_model,
        refined,
        noise,
        tuple(rounds),
        estimator,
        orders,
        withdrawn,
        checks.error(current, tuned=estimator == "output error"),
        pooled_period_noise(checked_whole(records)),
    )
    # The start as the loop makes it when it adds nothing (above): by output error where that
    # simulates the check blocks better and comes to rest.
    start, start_estimator = declared_model, estimator
    if current != declared_structure:
        start_estimator = "least squares"
        if output_error and checks.error(declared_structure, tuned=True) < checks.error(declared_structure):
            if declared_tuned is None:
                (declared_tuned,) = declared_search
            if declared_tuned is not declared_model and comes_to_rest(declared_tuned, records):
                start, start_estimator = declared_tuned, "output error"
    elif estimator == "output error":
        start = refined
    start_check = checks.error(declared_structure, tuned=start_estimator == "output error")
    folded = (before_folds, tuple(grown_across_folds)) if grown_across_folds else None
    return _Grown(refinement, start, start_estimator, start_check, current, folded)


def _scored(
    records: Records,
    current: Structure,
    offered: Sequence[Effect],
    alpha: float,
    workers: Workers,
    threads: Workers,
    rank: bool = False,
    kept: ScoringKept | None = None,
) -> Scores:
    """Every offered family's score against ``current``'s one-step residual
    (:func:`models.scoring.score_effects`); with ``rank``, with all its regressors ranked by error
    reduction, significant or not: what the simulation criteria try. ``kept``: the loop's
    scoring of a model, kept for its next scoring of the same model."""
    return score_effects(
        records,
        current.terms,
        current.noise_lags,
        offered,
        alpha,
        rank=rank,
        saturating=current.saturating,
        workers=workers,
        threads=threads,
        kept=kept,
    )


def _restless_then_rms(judged: tuple[float, bool]) -> tuple[bool, float]:
    """Sort key of a start: models that come to rest first, then by free-run RMS."""
    rms, at_rest = judged
    return not at_rest, rms


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

    **The constant.** An output at an operating point away from zero, its input about zero, is
    reached by an ARX without a constant only through poles near one: a model that integrates
    its own past, or one of needlessly high order. The orders chosen without a constant are
    judged with one too; where it lowers their figure beyond the spread, every order is judged
    with a constant as well and chosen among as above, the constant counted as one parameter
    more; of the two starts so chosen, the one with the constant is taken where it
    simulates better beyond ``margin`` and the spread, or as well and is smaller. On records
    about zero the constant takes nothing off, and the start stays as it was without the second
    set of fits.

    **Rectified.** With ``rectified``, every candidate is judged as a rectified model, its
    recursion read through a sensor of its magnitude (:mod:`models.narx`): the orders the
    rectified-output family starts from (:func:`_rectified_orders`).

    Returns (n, n, d) and the terms; ``progress`` is told each candidate as its figures are read,
    ``workers`` fit them (:data:`models.regression.Workers`).
    """
    if max_order < 1:
        raise InputError(f"the largest linear order must be 1 or more, got {max_order}")
    checks = checks or CheckSplit.of(records)
    folds = [checks, *(CheckSplit.of(records, fold) for fold in (0, 2))]
    tell = _told(progress)
    orders = [(n, d) for d in (1, 0) for n in range(1, max_order + 1)]
    samples = sum(len(y) for _, y in records)
    # The loop's level shared among every candidate's test, with a constant and without: on a
    # record of the rig, x[t-3]'s chance correlation with x[t-4] made ARX(3, 3)'s input
    # coefficients pass at the loop's level alone.
    level = DEFAULT_ALPHA / (2 * len(orders))
    judge = partial(_driven_figures, folds, records, level, workers=workers, tell=tell, rectified=rectified)
    smallest = partial(_smallest_driven, margin=margin, max_order=max_order, samples=samples)
    figures, admissible = judge([(n, d, False) for n, d in orders])
    n, d, _ = chosen = smallest(figures, admissible)
    constant, constant_admissible = judge([(n, d, True)])
    if _lower_beyond_spread(constant[(n, d, True)].figure, figures[chosen].figure):
        others = [(m, e, True) for m, e in orders if (m, e) != (n, d)]
        more, more_admissible = judge(others)
        constant |= more
        with_constant = smallest(constant, constant_admissible | more_admissible)
        # The two starts judged as the orders are: the one without a constant is kept unless the
        # other simulates better beyond the margin, or as well and is smaller.
        pair = {key: figures[key] if key == chosen else constant[key] for key in (chosen, with_constant)}
        n, d, _ = chosen = smallest(pair, set(pair))
    return (n, n, d), linear_terms(n, n, d, constant=chosen[2])


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
) -> tuple[dict[_Linear, _Judged], set[_Linear]]:
    """Each linear candidate's figures on the rotations of ``folds`` (:func:`_rotation_figures`);
    and those that may start the loop (:func:`choose_linear`). ``tell`` is told each candidate as
    its figures are read; ``workers`` judge them."""
    structures = [
        Structure(linear_terms(n, n, d, constant), rectified=rectified) for n, d, constant in candidates
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
) -> tuple[dict[_Linear, _Judged], set[_Linear]]:
    """:func:`_linear_figures`, each candidate's figures marked with whether the input drives it
    (:func:`models.input_drive.input_drives` at ``level`` on all the ``records``). A rectified
    model's linear terms read the recursion under the fold, which a linear fit of the readings
    does not: there every candidate counts as driven, judged by its free run alone."""
    figures, admissible = _linear_figures(folds, candidates, workers, tell, rectified)
    if not rectified:
        for n, d, constant in candidates:
            driven = input_drives(records, linear_terms(n, n, d, constant), level)
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
    difference across the rotations."""
    difference = other - figure
    return float(np.mean(difference)) > float(np.std(difference, ddof=1) / np.sqrt(difference.size))


def _smallest_driven(
    figures: dict[_Linear, _Judged], admissible: set[_Linear], margin: float, max_order: int, samples: int
) -> _Linear:
    """:func:`_smallest_near_best` among the admissible candidates the input drives (their input
    coefficients significant, :func:`_driven_figures`): on the rig's records with a sensor that
    clips, or a quadratic spring, every linear model runs free poorly and ARX(2, 2), whose input
    lags stop short of the rig's x[t-4] and whose input coefficients are nil, ran free as well as
    ARX(4, 4) and was the start. A candidate the input does not drive is taken only where none
    that it drives runs free without diverging, or where it runs free better than the best of
    those on every rotation, as a larger order is taken (on a short record of the rig with a
    strong quadratic spring, the driven orders diverged on a rotation or ran off by thousands of
    times the output's spread)."""
    chosen = _smallest_near_best(figures, admissible, margin, max_order, samples)
    pool = admissible or set(figures)
    driven = {key for key in pool if figures[key].driven and np.all(np.isfinite(figures[key].figure))}
    if figures[chosen].driven or not driven:
        return chosen
    best = _smallest_near_best({key: figures[key] for key in driven}, driven, margin, max_order, samples)
    return chosen if bool(np.all(figures[chosen].figure < figures[best].figure)) else best


def _smallest_near_best(
    figures: dict[_Linear, _Judged], admissible: set[_Linear], margin: float, max_order: int, samples: int
) -> _Linear:
    """The smallest admissible candidate near the best (:func:`choose_linear`): its mean figure,
    raised for its size on the ``samples`` held out (:func:`_size_penalty`), within ``margin`` of
    the best's so raised; or its figures above the best's by no more than the spread of their
    difference (a question of noise, which the size does not enter); or its instrumental-variable
    fit running free no worse than the best on one rotation at least. A larger order is taken only
    where it simulates better on every rotation, as a family is added across folds: a planted
    backlash's best linear approximation runs free a fifth better at order 5 than at 4 on two
    rotations, and worse on the third. The smaller order's own figure there is its
    instrumental-variable fit's: an output-error search from measured starts on short blocks can
    end well on one rotation by chance (on the rig, ARX(3, 3) with x[t], which cannot hold the
    input's delay of four samples, ran free over one rotation below ARX(4, 4))."""
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

    def near_best(key: _Linear) -> bool:
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


def _rectified_orders(
    records: Records, checks: CheckSplit | None, tell: Stage, workers: Workers
) -> tuple[Term, ...] | None:
    """Where the records' outputs read as a magnitude (:func:`models.effects.reads_magnitude`),
    the linear terms :func:`choose_linear` picks for the rectified model, which the rectified
    family starts from in the first round (:func:`_rectified_first`); None elsewhere. A sensor
    blind to the sign folds the output at zero, and a linear model of the readings fits the folds
    with other orders than the recursion under the fold wants (the coupled drives: (1, 1) and
    (2, 2) for the readings, three lags under the rectifier)."""
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


def _fitted_on_all(records: Records, structure: Structure) -> tuple[NARX, np.ndarray]:
    """``structure``'s least-squares fit on all the ``records`` (:func:`fit_model`)."""
    lag = max_lag(structure.terms)
    return fit_model(
        records,
        structure.terms,
        structure.noise_lags,
        lag,
        saturating=structure.saturating,
        rectified=structure.rectified,
    )


def _call(function: Callable[[], Any]) -> Any:
    """``function()``: what a worker runs to call a function prepared with its arguments."""
    return function()


def _with(score: EffectScore, kinds: dict[str, str], current: Structure, records: Records) -> list[Structure]:
    """The structures adding the scored effect may give: one, but two for output saturation
    (of the state or of the sensor), which adds limits rather than terms."""
    if kinds.get(score.name) == "saturation":
        limits = output_limits(np.concatenate([y for _, y in records]))
        if limits is None:
            return []
        return [replace(current, saturating=(limits, how)) for how in get_args(Saturation)]
    if kinds.get(score.name) == "rectified":
        return [_rectified(current)]
    if score.noise_lags:
        return [replace(current, noise_lags=score.noise_lags)]
    return [replace(current, terms=current.terms + parse_terms(score.terms))]


def _offered_again(effect: Effect, current: Structure) -> bool:
    """Whether ``effect`` is one the ``current`` structure has already: a saturating model is not
    offered saturation again, nor a rectified one the rectifier."""
    return (effect.kind == "saturation" and current.saturating is not None) or (
        effect.kind == "rectified" and current.rectified
    )


def _rectified(current: Structure, linear: Sequence[Term] | None = None) -> Structure:
    """``current`` read through a sensor of its magnitude, its recursion with a constant, and
    with the ``linear`` terms in place of its own where they are given: where the fold lies
    against the input's zero is the family's parameter, as a dead zone's width is (the coupled
    drives' second record, its input 0.5 above the first's: the rectified recursion runs free
    over the check blocks at 0.92 ticks/s without one)."""
    terms = current.terms if linear is None else tuple(linear)
    constant = () if Term() in terms else (Term(),)
    return replace(current, terms=terms + constant, rectified=True)


def _rectified_first(
    current: Structure,
    linear: Sequence[Term],
    offered: Sequence[Effect],
    scores: Sequence[EffectScore],
    checks: CheckSplit,
    workers: Workers,
) -> tuple[EffectScore, Criterion, Structure, float] | None:
    """The rectified-output family, where it is offered, taken before every other (the records'
    outputs read as a magnitude), from the ``linear`` terms chosen as the rectified model's,
    wherever its output-error fit runs free over the check blocks without diverging. A sensor's
    fold is no dynamics: judged after the families of the dynamics, one of them fitted to the fold
    stands in for it first, at the orders the readings chose. Least squares cannot see the fold
    (its fit is the recursion's on the readings): a rectified structure is fitted by output error
    (:class:`models.checking.CheckSplit`), and the check figure returned is that fit's.

    The evidence is the readings' shape, never below zero and down to it, not a gain on the check
    blocks: on a record of a few hundred samples the fit part lacks the swings through zero a
    check block holds, and the rectified fit extrapolates there (the coupled drives' second
    record: its one check block holds the widest swings, and the rectified fit runs free there
    worse than the linear start, while fitted on the fit and check parts together it runs the
    held-out tail at half the start's error). What the loop returns is judged against its start
    where no choice looked (:mod:`models.held_out`)."""
    for effect, score in zip(offered, scores, strict=True):
        if effect.kind != "rectified":
            continue
        structure = _rectified(current, linear)
        (error,) = checks.judge([structure], workers, tuned=True)
        if np.isfinite(error):
            # The report lists the terms the family brings beside the rectifier: its own lags.
            brought = tuple(t.name for t in structure.terms if t not in current.terms)
            return (
                replace(score, terms=(RECTIFIED, *brought)),
                "output's range",
                structure,
                checks.error(structure),
            )
    return None


def _simulated(offered: Sequence[Effect], scores: Sequence[EffectScore]) -> list[EffectScore]:
    """The scored families the simulation criteria grow the model by: those with ranked terms,
    neither noise, a sinusoid of the record's time, nor saturation."""
    return [
        score
        for effect, score in zip(offered, scores, strict=True)
        if effect.kind not in ("noise", "periodic", "saturation", "rectified") and score.ranked
    ]


def _judged_in_turn(
    scores: Sequence[EffectScore],
    kinds: dict[str, str],
    current: Structure,
    records: Records,
    checks: CheckSplit,
    workers: Workers,
    tell: Stage,
    stage: str,
) -> Generator[tuple[EffectScore, float, Structure], Matters | None, None]:
    """Each scored family in turn with its check blocks' free-run RMS and structure, the best
    of those adding it may give (:func:`_with`); ``tell`` is told each, in the ``stage``, as its
    judgement is read. ``JUDGED_AT_ONCE`` families are judged at a time by ``workers``: the round
    ends at the first that passes, and a family judged beside it is judged in vain. A caller that
    needs only the figures that matter to it sends which do (:meth:`CheckSplit.judge`'s
    ``matters``): the families judged from then on may give a bound for one that does not."""
    matters = None
    for first in range(0, len(scores), JUDGED_AT_ONCE):
        batch = [
            (score, _with(score, kinds, current, records)) for score in scores[first : first + JUDGED_AT_ONCE]
        ]
        errors = checks.judge(
            [option for _, options in batch for option in options], workers, matters=matters
        )
        for score, options in batch:
            tell(f"{stage}: {score.name} on the check blocks")
            error, structure = min(((next(errors), option) for option in options), key=lambda trial: trial[0])
            matters = (yield score, error, structure) or matters


def _looked_ahead(
    first: tuple[EffectScore, Criterion, Structure, float],
    judged: Generator[tuple[EffectScore, float, Structure], Matters | None, None],
    current: Structure,
    check: float,
    margin: float,
    ahead: Callable[[Structure, float], tuple[float, str | None, int]],
) -> tuple[tuple[EffectScore, Criterion, Structure, float], int]:
    """The family a round adds: ``first``, the first in the one-step order to clear the margin,
    unless one of the next ``CONTENDERS`` still ``judged`` takes a further ``SIMULATION_GAIN`` of
    the current model's figure ``check`` off the check blocks' free run and, each added in turn
    and the round after judged (``ahead``: the check figure that round ends at, the family it
    adds and the families it judged), the pair it starts ends lower by more than the figure's
    standard error ``margin``, and without the first; and how many candidates the look compared
    on the check blocks beside ``first`` (the contenders, and the families each round after
    judged), which the round reports among those it tried.

    The one-step order carries what the free run cannot: a family that explains more of the
    residual is more likely the effect, and an approximation of a missing effect can simulate the
    check blocks better until that effect is in (Silverbox from ``linear:4,4``: the cubic spring
    simulates them at half the missing lags' figure, and after it no named family's
    least-squares model runs free). But the first to clear can be a stand-in whose small gain
    hides the effect for good (Silverbox from ``linear:10,10``: a hysteresis variable at 0.85 of
    the figure where the offset reaches 0.38; with it in, the offset never entered). Neither
    gain alone tells these apart; the next round does: the effect leaves what remains to be
    found, a stand-in leaves its own error. A further gain of ``SIMULATION_GAIN``, what the
    simulation criterion asks of a family picked among many, decides when to look: any smaller is
    within what the best of several gains by chance on the same blocks. A later family
    that brings the first's terms among its own is that effect with more terms, not another (on
    the rig, whose structure holds a cubic spring, an offset brings every lag's square, a
    quadratic spring some of them); and where the later family's round adds the first, both pairs
    hold the same effects: in either case the one-step order names them. Moving-average
    noise, which clears by being no worse and is there to unbias the parameters, does not
    contend, and is not displaced.
    """
    _, criterion, structure, error = first
    if structure.noise_lags != current.noise_lags:
        return first, 0
    # The contenders judged from here need exact figures only where they could be chosen (a
    # partial, for the workers that judge them).
    contends = partial(_contends, check, margin, error)
    looked = list(islice(_sending(judged, contends), CONTENDERS))
    contenders = [
        (other_error, other, other_structure)
        for other, other_error, other_structure in looked
        if other_structure.noise_lags == current.noise_lags
        and other_error <= (1 - margin) * check
        and not set(structure.terms) <= set(other_structure.terms)
    ]
    if not contenders:
        return first, len(looked)
    best_error, best, best_structure = min(contenders, key=lambda trial: trial[0])
    if not contends(best_error):
        return first, len(looked)
    best_end, after_best, after_best_tried = ahead(best_structure, best_error)
    if after_best == first[0].name:
        return first, len(looked) + after_best_tried
    first_end, _, after_first_tried = ahead(structure, error)
    tried = len(looked) + after_best_tried + after_first_tried
    if best_end < (1 - margin) * first_end:
        return (best, criterion, best_structure, best_error), tried
    return first, tried


def _contends(check: float, margin: float, error: float, other_error: float) -> bool:
    """Whether a contender's check figure ``other_error`` clears the ``margin`` below ``check``
    and takes the further gain off the first's ``error`` (:func:`_looked_ahead`)."""
    return other_error <= (1 - margin) * check and error - other_error >= SIMULATION_GAIN * check


def _sending(
    judged: Generator[tuple[EffectScore, float, Structure], Matters | None, None], matters: Matters
) -> Iterator[tuple[EffectScore, float, Structure]]:
    """The families still to be ``judged`` in turn (:func:`_judged_in_turn`), told first which
    figures matter."""
    try:
        yield judged.send(matters)
    except StopIteration:
        return
    yield from judged


def _next_round(
    records: Records,
    families: Sequence[Effect],
    alpha: float,
    margin: float,
    checks: CheckSplit,
    workers: Workers,
    threads: Workers,
    tell: Stage,
    kept: ScoringKept,
    number: int,
    current: Structure,
    check: float,
) -> tuple[float, str | None, int]:
    """The check blocks' free-run RMS at which round ``number`` from ``current`` (running free
    there at ``check``) ends by the one-step criterion with least-squares parameters, the family
    it adds, and how many families it judged there; ``check`` and None where no named family
    clears (:func:`_looked_ahead`).
    Least squares alone, as the round looked from judged its families: a branch that only output
    error could carry on would otherwise win by the estimator (output error's figures run lower),
    not by its effect."""
    offered = [
        effect
        for effect in unused([_follow(effect, current.terms) for effect in families], current.terms)
        if effect.name != POLYNOMIAL and not (effect.kind == "saturation" and current.saturating is not None)
    ]
    tell(f"round {number}, looked ahead: scoring {len(offered)} families")
    scores = _scored(records, current, offered, alpha, workers, threads, kept=kept)
    kinds = {effect.name: effect.kind for effect in offered}
    significant = sorted((s for s in scores.scores if s.significant), key=lambda s: s.bic_change)
    stage = f"round {number}, looked ahead"
    judged = _judged_in_turn(significant, kinds, current, records, checks, workers, tell, stage)
    for tried, (score, error, structure) in enumerate(judged, start=1):
        if error <= (1.0 if structure.noise_lags > current.noise_lags else 1 - margin) * check:
            return min(error, check), score.name, tried
    return check, None, len(significant)


def _paired(
    significant: Sequence[EffectScore],
    kinds: dict[str, str],
    current: Structure,
    records: Records,
    check: float,
    checks: CheckSplit,
    ahead: Callable[[Structure, float], tuple[float, str | None, int]],
) -> tuple[tuple[tuple[EffectScore, Criterion, Structure, float], float] | None, int]:
    """Where no family clears on its own, the first ``significant`` family in the one-step order
    (not moving-average noise) added with the one the round after it adds (``ahead``, judged as
    :func:`_looked_ahead` judges a pair): its score, criterion, structure and check figure (worse
    than ``check`` alone), and the check figure the pair ends at, or None unless that end takes
    ``SIMULATION_GAIN`` of ``check`` off the check blocks' free run; and how many structures were
    judged on the check blocks to decide it.

    Two effects can each make the free run worse alone and simulate far better together: each
    alone is fitted to the other's share of the residual as well as its own. On the rig with
    Coulomb friction planted, nothing declared, the friction explains nearly all of the linear
    start's one-step residual, and alone runs free worse than the start, as does the rig's own
    cubic spring alone, which the friction's residual hides from the one-step tests; the two
    together run free at a small fraction of the start's figure. The family the residual names
    most strongly goes first; the next round, scored on its residual, finds its partner. The
    pair is picked through two rounds of choices, so it must take off what the simulation
    criterion asks of a family picked among many."""
    first = next((score for score in significant if not score.noise_lags), None)
    if first is None:
        return None, 0
    options = _with(first, kinds, current, records)
    judged = [(checks.error(option), option) for option in options if option.noise_lags == current.noise_lags]
    if not judged:
        return None, 0
    error, structure = min(judged, key=lambda trial: trial[0])
    if not np.isfinite(error):
        return None, len(judged)
    end, partner, partner_tried = ahead(structure, error)
    tried = len(judged) + partner_tried
    if partner is None or partner == first.name or end > (1 - SIMULATION_GAIN) * check:
        return None, tried
    return ((first, "pair", structure, error), end), tried


def _by_output_error_grown(
    significant: Sequence[EffectScore],
    kinds: dict[str, str],
    current: Structure,
    records: Records,
    check: float,
    margin: float,
    checks: CheckSplit,
    workers: Workers,
) -> tuple[EffectScore, Criterion, Structure, float] | None:
    """Where no ``significant`` family clears the one-step criterion by least squares, the first
    in the one-step order whose least-squares model diverges on the check blocks and which clears
    it by output error: its new terms added at zero to the current model's output-error fit,
    which runs free as that model does, and searched from there (:meth:`CheckSplit.search_grown`);
    its score, structure and check figure (by output error). None where none does.

    Least squares fits each lag's nonlinear term to the one-step residual, and on finely sampled
    data a small error in a lightly damped model's many coefficients makes the free run diverge,
    where the same terms with parameters fitted to the free run are an effect: on Silverbox from
    ``linear:10,10``, once the cubic spring and the offset are in, every family's least-squares
    model diverges there, and the loop stopped with the damping's and the spring's other terms
    missing. Such a family is judged against the current model's best figure, by least squares,
    by output error, or by output error searched as long again as the family is (its search
    starts where the current model's ended, and a longer search can gain on its own).
    A family whose least-squares model runs free and does not clear has been judged.
    """
    diverged = [
        (score, structure)
        for score in significant
        for structure in _with(score, kinds, current, records)
        if structure.noise_lags == current.noise_lags
        and structure.saturating == current.saturating
        and not np.isfinite(checks.error(structure))
    ]
    if not diverged:
        return None
    start = checks.tuned(current)
    longer = CheckSplit(checks.fit, checks.check, _tuned={current: start})
    further = longer.search(current, start, CHECK_EVALUATIONS)
    baseline = min(check, checks.error(current, tuned=True), further)
    for score, structure in diverged:
        (error,) = checks.search_grown(current, [structure], CHECK_EVALUATIONS, workers)
        if error <= (1 - margin) * baseline:
            return score, "output error", structure, error
    return None


def _by_simulation(
    offered: Sequence[Effect],
    scores: Sequence[EffectScore],
    current: Structure,
    checks: CheckSplit,
    workers: Workers,
) -> tuple[tuple[EffectScore, Criterion, Structure, float] | None, Gain | None, int]:
    """The family added on the simulation error alone, if one lowers the check blocks' free
    run enough (module docstring, step 4): its score with the terms that won, the structure, and
    the check blocks' free-run RMS with it (least squares, as the other rounds report it); the
    gain of that family by output error (else the best judged's, None where none was); and how
    many structures were simulated. The structures are judged by ``workers``."""
    families = [
        (
            score,
            [
                tuple(name for label in score.ranked[:k] for name in label)
                for k in range(1, len(score.ranked) + 1)
            ],
        )
        for score in _simulated(offered, scores)
    ]
    grown = {
        names: replace(current, terms=current.terms + parse_terms(names))
        for _, prefixes in families
        for names in prefixes
    }
    errors = dict(zip(grown, checks.judge(list(grown.values()), workers), strict=True))
    trials: list[tuple[float, EffectScore, Structure]] = []
    for score, prefixes in families:
        names = min(prefixes, key=errors.__getitem__)
        if np.isfinite(errors[names]):
            trials.append((errors[names], replace(score, terms=names), grown[names]))
    if not trials:
        return None, None, len(grown)
    # The current structure's best simulation, whichever its parameters: its output-error fit can
    # fail to come to rest where its least-squares fit does (on unrelated white x and y the 2-DOF
    # structure's did), and against an infinite baseline any family would pass.
    baseline = min(checks.error(current, tuned=True), checks.error(current))
    # Output error for the two best only: each costs a search, and a family whose least-squares
    # model is far behind does not overtake by its parameters alone.
    best = sorted(trials, key=lambda trial: trial[0])[:2]
    tuned = checks.judge([structure for *_, structure in best], workers, tuned=True)
    judged: Gain | None = None
    for (error, score, structure), tuned_error in zip(best, tuned, strict=True):
        gain = Gain(_fall(tuned_error, baseline), SIMULATION_GAIN)
        if tuned_error <= (1 - SIMULATION_GAIN) * baseline:
            return (score, "simulation", structure, error), gain, len(grown)
        judged = _better(judged, gain)
    return None, judged, len(grown)


class Gain(NamedTuple):
    """The fall of the check blocks' free-run RMS a candidate brought and the fall it had to
    reach to be added, both shares of the RMS before."""

    gain: float
    threshold: float


def _better(judged: Gain | None, other: Gain | None) -> Gain | None:
    """The larger gain of ``judged`` and ``other``, either None where not judged."""
    if judged is None or (other is not None and other.gain > judged.gain):
        return other
    return judged


def _fall(after: float, before: float) -> float:
    """The fall of a free-run RMS from ``before`` to ``after``, as a share of ``before``: −∞ where
    ``after`` diverged, 1 where only ``before`` did."""
    if not np.isfinite(after):
        return -np.inf
    return 1.0 if not np.isfinite(before) else float(1 - after / before)


def _pruned(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    checks: CheckSplit,
    workers: Workers,
    output_error: bool,
    alpha: float = DEFAULT_ALPHA,
) -> tuple[Structure, tuple[Term, ...]]:
    """``current``, grown from ``declared`` by the ``rounds``, pruned back (Piroddi & Spinelli
    2003, SEMP's pruning), and the terms taken out in turn.

    An effect picked on one round can be made useless by a later one it stood in for (a cubic
    spring fitted before the quadratic spring it imitated), and a family's terms ride in
    together though only some of them simulate: a term the rounds added goes where the check
    blocks' free-run RMS without it is no higher than the figure the rounds ended at, as SEMP's
    pruning keeps J within (1 + ρ) of J after the addition, here with ρ = 0. The bound is on that
    figure, not on the last removal's: a removal that lowered it leaves room for one that raises
    it as much, and removals one by one cannot creep above it. No rise is allowed, not even one
    within the figure's standard error: the check blocks see neither the model's extrapolation
    nor, on short records, more than a hundred samples, and with that much allowed Silverbox from
    linear:4,4 lost six terms and ran free over the arrow 15 % worse, and the coupled drives'
    second test lost four terms and with them, on the held-out tail, its effects.

    Once, after the rounds, not between them. A term pruned between rounds changes what every
    later round is offered and judged against, on a removal allowed for being no worse: on
    Silverbox from linear:10,10, two cubic terms pruned after round 2 left round 3 to quadratic
    stiffness, by the simulation criterion at the margin of its threshold, and that model drifted
    over Schroeder80mV, which neither the check blocks nor the held-out tails showed. After the
    rounds the effects are those the loop would choose unpruned, and the pruning only takes out
    what their structure does not need.

    It takes terms, never a named effect: an effect's last term stays. Its round added it for a
    fall of the free run beyond a threshold; "no higher without it" on the same check blocks is
    far weaker evidence, and those blocks see neither the model's long-run drift nor its
    extrapolation. An effect is withdrawn whole by the checks that judge effects: the
    output-error check of what the rounds added and the held-out tails. The generic polynomial
    is the exception: it names nothing, and where a later round added a named effect it may
    have stood in for, the pruning tries it whole (:func:`_generic_blocks`; its round then
    reports it pruned whole).

    Three passes, each judging few structures, since judging every removal on the free run,
    again after each one taken, costs a fit and a free run a term a removal (on long records as
    much as the rounds): the generic blocks whole; then the terms not significant at the loop's
    level ``alpha`` in the least-squares fit on the check split's fit parts, the smallest t
    statistic first, as many together as pass (:func:`_largest_batch`), again on what is left
    after each batch taken; then, one term at a time, the best ``PRUNING_TRIALS``
    of what is left by t statistic, ranked again after each removal, until both are refused. A
    removal is judged as the model will be fitted: its least-squares free run within the bound
    and, where the current structure simulates better by output error (``output_error``: as the
    loop will then fit it), its output-error fit's within the bound on that fit's figure; a term
    of no use to the one-step fit's free run can be one the output-error fit needs (judged by
    least squares alone, Silverbox from linear:4,4 lost such terms and ran free over the arrow
    worse). The least-squares judgements are made by ``workers``.
    """
    ceiling = _ceiling(current, checks, output_error)
    if ceiling is None:
        return current, ()
    pruned: list[Term] = []

    def took(found: tuple[tuple[Term, ...], Structure] | None) -> bool:
        nonlocal current
        if found is not None:
            taken, current = found
            pruned.extend(taken)
        return found is not None

    for block in _generic_blocks(current, rounds):
        took(_first_removal(current, [block], ceiling, checks, workers))
    while took(
        _largest_batch(
            current,
            _insignificant(current, declared, rounds, pruned, checks, alpha),
            ceiling,
            checks,
            workers,
        )
    ):
        pass
    while took(
        _first_removal(
            current,
            [(term,) for term, _ in _removals(current, declared, rounds, pruned, checks)[:PRUNING_TRIALS]],
            ceiling,
            checks,
            workers,
        )
    ):
        pass
    return current, tuple(pruned)


class _Ceiling(NamedTuple):
    """The check blocks' free-run RMS a pruned structure may reach (:func:`_pruned`): by least
    squares, and by output error where that is how the structure simulates better (else None)."""

    least_squares: float
    output_error: float | None


def _ceiling(current: Structure, checks: CheckSplit, output_error: bool) -> _Ceiling | None:
    """The bounds :func:`_pruned` holds ``current``'s removals to: its figures on the check blocks;
    None where neither figure is finite (no removal could be judged)."""
    figure = checks.error(current)
    simulated = checks.error(current, tuned=True) if output_error else np.inf
    if not np.isfinite(min(figure, simulated)):
        return None
    return _Ceiling(figure, simulated if simulated < figure else None)


def _first_removal(
    current: Structure,
    trials: Sequence[tuple[Term, ...]],
    ceiling: _Ceiling,
    checks: CheckSplit,
    workers: Workers,
) -> tuple[tuple[Term, ...], Structure] | None:
    """The first of the ``trials`` (each terms taken out together) whose removal :func:`_pruned`
    takes, with ``current`` without it; None where none is. Their least-squares fits are judged
    by ``workers``, side by side; the output-error fits, which cost far more, only where a
    removal passes by least squares, and the next only where the one before is refused."""
    without = [replace(current, terms=tuple(t for t in current.terms if t not in trial)) for trial in trials]
    for trial, structure, error in zip(trials, without, checks.judge(without, workers), strict=True):
        if error <= ceiling.least_squares and (
            ceiling.output_error is None or checks.error(structure, tuned=True) <= ceiling.output_error
        ):
            return trial, structure
    return None


def _generic_blocks(current: Structure, rounds: Sequence[Round]) -> list[tuple[Term, ...]]:
    """The terms of ``current`` each round that added the generic polynomial brought, where a
    later round added an effect: the blocks :func:`_pruned` tries whole."""
    added = [step.added for step in rounds if step.added is not None]
    present = {term.name: term for term in current.terms}
    blocks = [
        tuple(present[name] for name in score.terms if name in present)
        for score in added[:-1]
        if score.name == POLYNOMIAL
    ]
    return [block for block in blocks if block]


def _insignificant(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    pruned: Sequence[Term],
    checks: CheckSplit,
    alpha: float,
) -> list[Term]:
    """The terms :func:`_removals` offers whose t statistic is not significant at the level
    ``alpha`` (two-sided), smallest first, as many of an effect's as leave it one."""
    effect = _effect_of(rounds, pruned)
    left = Counter(effect.values())
    critical = z_quantile(1 - alpha)
    batch = []
    for term, t in _removals(current, declared, rounds, pruned, checks):
        if t < critical and (term.name not in effect or left[effect[term.name]] > 1):
            left[effect.get(term.name)] -= 1
            batch.append(term)
    return batch


def _effect_of(rounds: Sequence[Round], pruned: Sequence[Term]) -> dict[str, int]:
    """Each term the ``rounds`` added and the pruning has left, by name, with the round that
    added it (its index)."""
    gone = {term.name for term in pruned}
    return {
        name: index
        for index, step in enumerate(rounds)
        if step.added is not None
        for name in step.added.terms
        if name not in gone
    }


def _largest_batch(
    current: Structure, batch: Sequence[Term], ceiling: _Ceiling, checks: CheckSplit, workers: Workers
) -> tuple[tuple[Term, ...], Structure] | None:
    """The most of ``batch``'s first terms whose removal together :func:`_pruned` takes, found by
    doubling them (one, two, four …, then all) while the removal passes, with ``current``
    without them; None where the first alone is refused. Upwards, not down from the whole: on a
    long model, removing most of its terms at once is refused far more often than a few, and a
    refused first term then costs one judgement, not one for each halving (Silverbox from
    linear:10,10: 226 terms not significant, each halving refused down to the first)."""
    taken = None
    size = 1
    while batch:
        found = _first_removal(current, [tuple(batch[:size])], ceiling, checks, workers)
        if found is None:
            break
        taken = found
        if size == len(batch):
            break
        size = min(2 * size, len(batch))
    return taken


def _removals(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    pruned: Sequence[Term],
    checks: CheckSplit,
) -> list[tuple[Term, float]]:
    """The terms of ``current`` :func:`_pruned` may take out with their t statistic in its
    least-squares fit on the check split's fit parts, the smallest first: those the ``rounds``
    added, but for the last one left of an effect once ``pruned`` are out."""
    effect = _effect_of(rounds, pruned)
    left = Counter(effect.values())
    removable = [
        i
        for i, term in enumerate(current.terms)
        if term not in declared and (term.name not in effect or left[effect[term.name]] > 1)
    ]
    if not removable:
        return []
    fitted = checks.fitted(current)
    t = np.abs(fitted.theta) / np.maximum(fitted.standard_errors(), np.finfo(float).tiny)
    return [(current.terms[i], float(t[i])) for i in sorted(removable, key=lambda i: t[i])]


def _without_pruned(rounds: list[Round], pruned: Sequence[Term]) -> list[Round]:
    """The ``rounds`` with the ``pruned`` terms taken from the effects that brought them, named in
    the last round's report; a round whose effect lost every term is marked pruned whole."""
    names = {term.name for term in pruned}
    if not names:
        return rounds
    result = []
    for step in rounds:
        added = step.added
        if added is not None and names & set(added.terms):
            left = tuple(n for n in added.terms if n not in names)
            step = replace(step, added=replace(added, terms=left), pruned_whole=not left)
        result.append(step)
    result[-1] = replace(result[-1], pruned=tuple(term.name for term in pruned))
    return result


def _repairs_only_bias(
    declared: Structure, current: Structure, check: float, folds: Sequence[CheckSplit], workers: Workers
) -> bool:
    """Whether what the rounds added to ``declared`` should be withdrawn: with output-error
    parameters the declared structure simulates the check parts at least as well as ``current``
    (whose least-squares figure there is ``check``) or, from three records on, at least as well
    on one of the ``folds``, both searched until they stop gaining.

    Effects that helped least-squares parameters but not output-error ones repaired the noise's
    bias, not the dynamics (F-16's acceleration 2: friction and backlash added on tenths of a per
    cent, 12–39 % worse on the test levels once tuned); and on sweeps, effects added on one check
    record's gains of tenths of a per cent need not carry over to the others. The two searches
    on the check parts are made side by side by ``workers``.
    """
    checks = folds[0]
    current_error, declared_error = checks.judge([current, declared], workers, tuned=True)
    if declared_error <= min(check, current_error):
        return True
    if len(folds) == 1:
        return False
    checks.settled(declared)
    return _on_every_fold(declared, current, folds, checks.grown(declared, current), gain=0.0) is None


def _across_folds(
    offered: Sequence[Effect],
    scores: Sequence[EffectScore],
    current: Structure,
    folds: Sequence[CheckSplit],
    tell: Stage,
    workers: Workers,
) -> tuple[EffectScore, Structure, tuple[float, float]] | None:
    """The family added on the simulation error across folds (module docstring), if one
    lowers every fold's free run by ``FOLD_GAIN``: its score with all its terms, the structure,
    and the first fold's free-run RMS before and after, both settled.

    Each family's terms are all grown at zero from ``current``'s settled output-error fit, which
    simulates as that model does, so that a search cannot end worse than it, and none is asked to
    repair dynamics that a least-squares start got wrong (every cubic-stiffness prefix fitted by
    least squares diverges over F-16's check sweep). The first fold ranks the families by bounded
    searches; the best ``FOLD_TRIALS`` are settled on every fold, the first fold first, and of
    those that gain on all of them the one whose free run falls most, on average over the folds
    as a share of the current model's, is added (on F-16's acceleration 3 that was power-law
    stiffness, until the models were held to measured states). The refined model is then fitted
    on all the records as the folds fitted theirs (:func:`_as_the_folds_judged`). The first fold's
    searches are made by ``workers``; ``tell`` is told each family as its searches begin (or, made
    by workers, are waited for).
    """
    primary = folds[0]
    if not np.isfinite(base := primary.settled(current)):
        return None
    families = [
        (score, tuple(name for label in score.ranked for name in label))
        for score in _simulated(offered, scores)
    ]
    structures = [replace(current, terms=current.terms + parse_terms(names)) for _, names in families]
    searched = primary.search_grown(current, structures, CHECK_EVALUATIONS, workers)
    trials: list[tuple[float, EffectScore, Structure]] = []
    for (score, names), structure in zip(families, structures, strict=True):
        tell(f"across folds: {score.name} on the first fold")
        error = next(searched)
        if error <= (1 - FOLD_GAIN) * base:
            trials.append((error, replace(score, terms=names), structure))
    passed: list[tuple[float, EffectScore, Structure, tuple[float, float]]] = []
    for _, score, structure in sorted(trials, key=lambda trial: trial[0])[:FOLD_TRIALS]:
        tell(f"across folds: {score.name} on every fold")
        errors = _on_every_fold(current, structure, folds, primary.tuned(structure), FOLD_GAIN)
        if errors is not None:
            passed.append(
                (float(np.mean([after / before for before, after in errors])), score, structure, errors[0])
            )
    if not passed:
        return None
    _, score, structure, first_fold = min(passed, key=lambda trial: trial[0])
    return score, structure, first_fold


def _as_the_folds_judged(
    records: Records,
    before: Structure,
    grown: Sequence[Structure],
    declared: Structure,
    declared_tuned: NARX,
    threads: Workers,
) -> NARX:
    """The output-error fit on all the ``records`` of the structure grown across folds, made as
    each fold made the model it judged: ``before``'s settled fit (the declared structure's is
    ``declared_tuned``), then each of the ``grown`` structures in turn, its added terms at zero
    from the fit before it, searched until it stops gaining (the Jacobians factored by ``threads``).

    The folds validate a procedure, not a model: the model delivered is that procedure applied to
    all the data (Hastie, Tibshirani & Friedman, *The Elements of Statistical Learning*, §7.10).
    Searched from the first fold's fit instead, whose search began on two thirds of the records,
    F-16's acceleration 3 with power-law stiffness ended 0.7 % lower on the estimation records and
    60 % higher on the test sweep below their levels (0.344 against 0.215 m/s²).
    """
    everything: Segments = [(x, y, 0) for x, y in records]
    model = (
        declared_tuned
        if before == declared
        else by_output_error(_fitted_on_all(records, before)[0], everything, SETTLED_EVALUATIONS, threads)
    )
    for structure in grown:
        start = grown_by_zeros(model, _fitted_on_all(records, structure)[0])
        model = by_output_error(start, everything, SETTLED_EVALUATIONS, threads)
    return model


def _on_every_fold(
    current: Structure,
    structure: Structure,
    folds: Sequence[CheckSplit],
    first_start: NARX | None,
    gain: float,
) -> list[tuple[float, float]] | None:
    """Each fold's free-run RMS over its checked records of ``current`` and of ``structure``
    (grown from it), both settled, while ``structure`` lowers it by more than the share ``gain``;
    None from the first fold where it does not. The first fold's search starts from
    ``first_start``, the others' from ``current``'s settled fit grown by zeros."""
    errors = []
    for fold in folds:
        before = fold.settled(current)
        start = first_start if fold is folds[0] else fold.grown(current, structure)
        errors.append((before, fold.settled(structure, start)))
        if not errors[-1][1] < (1 - gain) * before:
            return None
    return errors


def _check_length(records: Records, terms: tuple[Term, ...], offered: Sequence[Effect]) -> None:
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in offered if e.terms])
    candidates = sum(e.regressors for e in offered)
    n = sum(len(y) - lag for _, y in records)
    needed = 2 * (len(terms) + candidates) + 1
    if n < needed or any(len(y) <= lag + 3 * MIN_BLOCK // 10 for _, y in records):
        raise InputError(
            f"the estimation records have {n} equations ({', '.join(str(len(y)) for _, y in records)} "
            f"samples); refining {len(terms)} terms with {candidates} candidates needs at least "
            f"{needed}, and each record more than {lag + 3 * MIN_BLOCK // 10} samples"
        )


def _follow(effect: Effect, terms: tuple[Term, ...]) -> Effect:
    """An output-shift effect brings the terms the current model's offset would."""
    if effect.kind != "output_shift":
        return effect
    return Effect(effect.name, effect.description, offset_terms(terms), effect.kind)
