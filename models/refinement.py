"""Closing the loop (SPEC §7): residual → the effect the model lacks → refined model.

Starting from a declared structure (or, with none declared, from a linear model whose orders the
loop chooses, :mod:`models.linear_start`), each round (:mod:`models.growing`, its criteria in
:mod:`models.round_criteria`)

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
   current figure and, each added and the next round judged, ends lower
   (:func:`models.round_criteria.looked_ahead`).
   Where none clears, a family whose least-squares model diverges there is judged by output
   error, grown from the current model's output-error fit
   (:func:`models.round_criteria.by_output_error_grown`);
4. if no effect is significant on e (on slow, finely sampled data the one-step residual carries
   little of the simulation error), or every significant one made the free run worse, each
   family's regressors are tried in the order of their error reduction, and the family whose
   model (parameters refined by output error, as is the current model's) lowers the check
   blocks' free-run RMS by at least ``SIMULATION_GAIN`` is added — decided by the simulation
   criterion. Where none does, the first significant family is judged with the family the
   round after it adds (:func:`models.round_criteria.as_pair`): two effects can each run free
   worse alone and far better together; so it is too where that first ran free worse alone and a
   later family cleared step 3 by less than ``SIMULATION_GAIN``
   (:func:`models.round_criteria.leader_as_pair`). Otherwise the loop stops.

After the rounds, the loop prunes back the terms they added that the check blocks' free run does
not need (:mod:`models.pruning`). Each round reports the candidates it compared on the check
blocks' free run, and the fall of that free run the effect added brought (else the best judged)
against the fall it had to reach; the last, what the pruning took out.

The generic polynomial (:func:`models.effects.polynomial_effect`, products of two of the model's
lags, no physical effect named) is scored with the named families but judged after them: steps 3
and 4 run for the named families first, and only where neither adds one for the polynomial.

After the rounds, the refined structure must simulate the check blocks better than the declared
one, both with their parameters by output error (from three records on, on every fold below);
otherwise what the rounds added is withdrawn and the declared structure kept
(:func:`models.across_folds.repairs_only_bias`).

**Across folds.** From three records on, the structure kept is then grown on the simulation
error across folds, each third of the records checked in turn and the rest fitted
(:mod:`models.across_folds`).

**Never worse.** The rounds choose among many candidates on the same check blocks, and the best
of many gains there by chance: where the records are long enough, the loop runs on each record's
first part only, and the model it refines is compared with its start on the records' tails,
which no choice saw (:mod:`models.held_out`). Unless it simulates them better beyond the
comparison's uncertainty, the start is returned and the report says the data could not support
the effects, naming the best one tried; so it is where the refined model holds a law of the
output kinked at a zero the records come near but never reach, whose mirror across it no record
judged (:mod:`models.kinks`). The start there is its least-squares fit where that
simulates the tails better than its output-error fit beyond the same uncertainty
(:func:`_start_on_tails`), and so is the refined model on tails of a block or more
(:func:`_refined_on_tails`). Whichever is returned has its parameters estimated on all the records
as the loop estimated them on its part (:func:`refine`), an output-error fit there only where it
holds as the model the tails approved does (:func:`_holds_as_approved`).

**Short records.** Tails shorter than ``MIN_BLOCK`` (records of a few hundred samples, down to
``models.held_out.MIN_TAIL``) are held out as well (:func:`refine`), with two differences. The
linear start is chosen on the whole records, not the heads: a fifth fewer of a few hundred samples moves the
orders (the coupled drives' PRBS record at ±1: (10, 10, 0) on its first 320 samples, running
free over the test at 1.24 ticks/s, against (1, 1, 1) and 0.66 on all 400), and the tails'
part in that choice can only favour the start, the side the comparison errs to. The start is
fitted by output error only where that runs free over the tails no worse than least squares,
whatever the comparison's uncertainty (:func:`_start_on_tails`). And moving-average noise alone
must simulate the tails better, like any effect: over three blocks the comparison's uncertainty
is a large share of the mean square, and "no worse beyond it" kept noise terms that took the
drives' test free run from 0.662 to 0.677 ticks/s.

**Settling.** Where the records start before the system settled (a machine warming up from rest)
and the held-out tails show it, the model is estimated from where they settled
(:mod:`models.settling`).

**The noise model.** Once the model returned is made, moving-average noise the rounds did not add
(its re-estimated process ran free worse) is offered on that model's own one-step residual and,
where its lags whiten it significantly, reported as the noise model, the process left as it was
(:mod:`models.noise_model`).

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

The refinement and its report, and how both are written out, are in
:mod:`models.refinement_report`.

Where the checked records repeat their excitation, the spread between periods gives the noise no
model can simulate (:mod:`models.periods`). Reported beside the check blocks' free run, it says how
much of that figure any model could still take off: on the Wiener–Hammerstein records, whose
process noise is 86 mV RMS, the linear model's figure is within half a per cent of it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from functools import partial
from itertools import pairwise

import numpy as np

from models.across_folds import as_the_folds_judged
from models.amplitude_range import amplitude_ranges
from models.assessment import assess, check_test_length
from models.checking import (
    MIN_BLOCK,
    SETTLED_EVALUATIONS,
    CheckSplit,
    Segments,
    Structure,
    by_output_error,
    checked_whole,
    free_run_rms,
    grown_by_zeros,
)
from models.coverage import coverage
from models.effects import MOVING_AVERAGE_NOISE, Effect, candidate_effects, linear_terms
from models.errors import InputError
from models.growing import Grown, loop_on, restless_then_rms
from models.held_out import HeldOut, compare_on_tails, held_out_tails
from models.kinks import kinks_beyond_the_records
from models.linear_start import MAX_LINEAR_ORDER, choose_linear, rectified_orders
from models.narx import NARX
from models.noise_model import with_noise_model
from models.output_error import comes_to_rest, free_run_at_rest, rings_from_measured
from models.periods import pooled_period_noise
from models.refinement_report import (
    Comparison,
    Criterion,
    Estimator,
    Refinement,
    RefinementReport,
    Round,
    Stage,
    Verdict,
    told,
)
from models.regression import Workers
from models.round_criteria import DEFAULT_ALPHA, fitted_on_all
from models.rounds_on_tails import best_rounds_on_tails
from models.scoring import Records
from models.settling import of_time, settled_from
from models.signals import GLITCH_FACTOR, glitches
from models.terms import Term, max_lag, parse_terms

MAX_ROUNDS = 10
# Glitches a report names by their sample; more are counted.
GLITCHES_NAMED = 5


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
    told(progress)("judging both models on the test part")
    t0 = c - estimation[0][0]  # the test part's time from the first part's start
    comparison = compare(result, estimation_part, x[c:d], y[c:d], initial, fs, t0)
    notes = _notes(len(estimation)) + _glitch_notes(
        estimation_part,
        lambda signal, part, index: f"{signal}[{estimation[part][0] + index}]",
        "leave it out with estimation parts around it",
    )
    ranges = amplitude_ranges(result.declared, result.refined, estimation_part)
    return RefinementReport(result, (comparison,), notes, ranges)


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
    tell, comparisons = told(progress), []
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
    if of_time(result.refined.terms):
        notes += (
            "the refined model's periodic terms keep the phase of the estimation record's first "
            "sample; the test records share no time base with it, so those terms are not validated there",
        )
    ranges = amplitude_ranges(result.declared, result.refined, estimation)
    return RefinementReport(result, tuple(comparisons), notes, ranges)


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
    if len(estimation) > 1 and declared and of_time(parse_terms(declared)):
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

    ``declared`` None starts from the linear model :func:`models.linear_start.choose_linear` picks.
    ``effects`` are the families on offer, by default :func:`models.effects.candidate_effects` of
    the declared terms: sized to the declared lags, so that the loop explains the residual with the
    declared dynamics rather than by lengthening them round after round. An offset's terms follow
    the model as it grows. ``output_error`` False keeps least-squares parameters throughout.
    ``progress`` is told each stage as it begins. ``workers`` run the loop's independent pieces
    (:data:`models.regression.Workers`): each round's searched candidates, the structures judged on
    the check parts, the output-error searches not needed one after the other; ``threads``, a map
    over threads of this process, test each round's families (:func:`models.scoring.score_effects`).
    The refinement is the same whichever.

    **Never worse.** Where every record is long enough (:func:`models.held_out.held_out_tails`),
    the last ``HELD_OUT_SHARE`` of each is held out from every choice (orders, effects, estimator):
    the loop runs on the rest, and the model it refines is kept only where its free run over
    those tails is better than the start's beyond the comparison's uncertainty
    (:func:`models.held_out.compare_on_tails`; moving-average noise alone, which leaves the
    process structure as it was, need only not be worse); over tails of ``MIN_BLOCK`` samples or
    more, the model of the loop's first rounds takes its place where that runs free over them
    lower and is kept as well (:mod:`models.rounds_on_tails`). Otherwise the start is returned, every
    round counted as withdrawn, and ``held_out`` names the best effect tried. The start is fitted
    by least squares, not output error, where least squares' fit simulates those tails better
    beyond the comparison's uncertainty (:func:`_start_on_tails`). The structure so judged then
    has its parameters estimated on all the records as the loop estimated them on the rest
    (:func:`_on_all`): the tails judged a procedure, and the model it makes gains from every
    sample. Records of a few hundred samples are held out from as well (module docstring).
    """
    tell = told(progress)
    if not 0 < alpha < 1:
        raise InputError(f"alpha must lie in (0, 1), got {alpha}")
    records = [(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)) for x, y in records]
    grow = partial(
        loop_on,
        declared=declared,
        effects=effects,
        alpha=alpha,
        max_rounds=max_rounds,
        output_error=output_error,
        tell=tell,
        workers=workers,
        threads=threads,
        ranged_by=records,
    )
    refined, estimated_on = _grown_and_judged(records, grow, declared, output_error, tell, workers, threads)
    # The noise model after the process effects are settled (models.noise_model), where the
    # families on offer include noise.
    family = MOVING_AVERAGE_NOISE if effects is None or MOVING_AVERAGE_NOISE in effects else None
    return with_noise_model(refined, estimated_on, family, alpha)


def _grown_and_judged(
    records: Records,
    grow: Callable[..., Grown],
    declared: Sequence[str | Term] | None,
    output_error: bool,
    tell: Stage,
    workers: Workers,
    threads: Workers,
) -> tuple[Refinement, Records]:
    """The loop ``grow`` run on the ``records``' heads and judged on their tails where they are
    long enough, on all of them otherwise (:func:`refine`'s never worse), and the records the
    returned model's parameters were estimated on (from where each settled)."""
    split = held_out_tails(records)
    if split is None:
        return grow(records).refinement, records
    heads, tails = split
    # The least-squares fit on all the records of the structure the loop refines, made by a worker
    # while the loop searches that structure's parameters on the heads by output error, where
    # the workers are idle: the model the tails keep is estimated again on all the records
    # (:func:`_on_all`), and its search there starts from the best of that fit and others.
    fitted_ahead: dict[Structure, Iterable[tuple[NARX, np.ndarray]]] = {}

    def fit_ahead(structure: Structure) -> None:
        fitted_ahead[structure] = workers(partial(fitted_on_all, records), [structure])

    short = any(len(y) < MIN_BLOCK for _, y, _ in tails)
    orders_saw_tails = short and declared is None
    if orders_saw_tails:
        orders, terms = choose_linear(records, progress=tell, workers=workers)
        rectified = rectified_orders(records, None, tell, workers)
        grow = partial(grow, declared=terms, orders=orders, rectified=rectified)
    try:
        grown = grow(heads, on_structure=fit_ahead)
    except InputError:
        # Too few equations for the candidates once the tails are held out: refined on all of
        # them, with nothing to compare on (the report says so).
        return grow(records).refinement, records
    grown = _start_on_tails(grown, heads, tails, short)
    if not short:
        grown = _refined_on_tails(grown, heads, tails)
    held_out = _judged_on_tails(grown, heads, tails, short, orders_saw_tails, tell)
    if held_out is not None and held_out.kept and not short:
        grown, held_out = _best_rounds(grown, held_out, heads, tails, orders_saw_tails, tell)
    settled = settled_from(grown, held_out, heads, tails, tell)
    if not any(settled):
        ahead = fitted_ahead.get(grown.structure)
        return _on_all(grown, held_out, records, output_error, tell, threads, ahead), records
    settled_records = [(x[cut:], y[cut:]) for (x, y), cut in zip(records, settled, strict=True)]
    refined = _on_all(grown, held_out, settled_records, output_error, tell, threads)
    return replace(refined, settled_from=settled), settled_records


def _judged_on_tails(
    grown: Grown, heads: Records, tails: Segments, short: bool, orders_saw_tails: bool, tell: Stage
) -> HeldOut | None:
    """The refined model beside the start on the held-out ``tails`` where the loop added an
    effect (:func:`models.held_out.compare_on_tails`), its ``kept`` false where the tails do not
    support it, or where it holds laws of the output that change form at zero, a zero the
    records (``heads`` and ``tails``) never reached but come near (:mod:`models.kinks`); None
    where nothing was added.

    The tails lie within the records' range, as every check block does: a law that fits the
    records there and mirrors itself across a zero beyond them passes them all, and a record
    that crosses that zero finds the model's restoring force where the law put it."""
    result = grown.refinement
    if not result.effects_added:
        return None
    tell("the refined model and the start on the held-out tails")
    refined, start = result.refined, grown.start
    kinks = kinks_beyond_the_records(start, refined, [*heads, *((x, y) for x, y, _ in tails)])
    held_out = replace(
        compare_on_tails(start, refined, tails, heads=heads),
        orders_saw_tails=orders_saw_tails,
        kinks_beyond=kinks,
    )
    # Moving-average noise alone, there to unbias the parameters, leaves the process
    # structure as it was: on long tails it need only not make the free run worse.
    noise_only = refined.terms == start.terms and refined.output_limits == start.output_limits
    if kinks or not (held_out.better or (noise_only and not short and held_out.not_worse)):
        held_out = replace(held_out, kept=False, best_tried=_best_tried(result.kept))
    return held_out


def _best_rounds(
    grown: Grown,
    held_out: HeldOut,
    heads: Records,
    tails: Segments,
    orders_saw_tails: bool,
    tell: Stage,
) -> tuple[Grown, HeldOut]:
    """``grown`` and its comparison ``held_out`` with the start, which kept it, or the model of its
    first rounds where that ran free over the ``tails`` lower and is kept as well
    (:mod:`models.rounds_on_tails`), the later rounds' effects set aside. Not over short tails
    (:func:`_grown_and_judged`): one free run of a hundred samples tells nested models apart by
    chance (on the DC motor's 500-sample estimation half, the model of its first three rounds ran
    its tails lower and the test half a sixth worse than the six rounds' model)."""
    tell("the rounds' models on the held-out tails")
    earlier = best_rounds_on_tails(grown, heads, tails, held_out.refined_rms)
    if earlier is None:
        return grown, held_out
    judged = _judged_on_tails(earlier, heads, tails, False, orders_saw_tails, tell)
    if judged is None or not judged.kept:
        return grown, held_out
    set_aside = [step.added.name for step in earlier.refinement.rounds if step.set_aside and step.added]
    return earlier, replace(
        judged, set_aside=tuple(dict.fromkeys(set_aside)), all_rounds_rms=held_out.refined_rms
    )


def _start_on_tails(grown: Grown, heads: Records, tails: Segments, short: bool) -> Grown:
    """``grown`` with its start by least squares where the loop chose output error for it on the
    ``heads``' check blocks and the ``tails`` say least squares simulates better: over ``short``
    tails, by its free run alone; over longer ones, beyond the comparison's uncertainty
    (:func:`models.held_out.compare_on_tails`).

    On a few hundred samples that choice rests on a free run over a hundred, and the tails judge
    it as they judge the effects (the coupled drives' PRBS records: output error chosen on 320
    samples ran free over the test 3–6 % worse than least squares). On longer records the check
    blocks judge the output-error fit on their fit blocks, not the start's fit on all the heads,
    and that search can end at another optimum: a slow pole all but cancelled by a zero, which the
    input hardly drives and a free run started from measured outputs elsewhere sets ringing for
    thousands of samples, far beyond the records' range. The start is the model every effect is
    judged against on the tails and the model returned when none is kept: one that diverges
    there would let anything pass as "not worse" and be returned itself."""
    if grown.start_estimator != "output error":
        return grown
    least_squares = grown.refinement.declared
    if short:
        if free_run_rms(grown.start, tails, heads) <= free_run_rms(least_squares, tails, heads):
            return grown
    elif not compare_on_tails(grown.start, least_squares, tails, heads=heads).better:
        return grown
    check = CheckSplit.of(heads).error(Structure(least_squares.terms))
    return grown._replace(start=least_squares, start_estimator="least squares", start_check=check)


def _refined_on_tails(grown: Grown, heads: Records, tails: Segments) -> Grown:
    """``grown`` with its refined model by least squares where the loop chose output error for it
    on the ``heads``' check blocks and the least-squares fit of the same structure simulates the
    ``tails`` better beyond the comparison's uncertainty (:func:`models.held_out.compare_on_tails`),
    as :func:`_start_on_tails` chooses the start's estimator.

    The check blocks compare the two estimators on fits to the fit blocks; the model returned is
    the search on all the heads, which can end elsewhere: on 4000 samples of the rig with a dead
    zone, nothing declared, the output-error fit of the dead zone and the rig's spring ran free
    over the tails several times as far off as the least-squares fit of the same terms, and over
    another seed's record several times as far as the model refined from the rig's structure.
    Moving-average noise alone leaves the start's process terms, whose estimator the start's own
    choice settled: it is passed over."""
    result = grown.refinement
    noise_only = result.refined.terms == grown.start.terms
    if (
        result.estimator != "output error"
        or not result.effects_added
        or noise_only
        or grown.folded is not None
    ):
        return grown
    fitted = grown.least_squares  # the structure's least-squares fit on all the heads
    if not compare_on_tails(result.refined, fitted, tails, heads=heads).better:
        return grown
    check = CheckSplit.of(heads).error(grown.structure)
    return grown._replace(
        refinement=replace(result, refined=fitted, estimator="least squares", check_rms=check)
    )


def _on_all(
    grown: Grown,
    held_out: HeldOut | None,
    records: Records,
    output_error: bool,
    tell: Stage,
    threads: Workers,
    fitted_ahead: Iterable[tuple[NARX, np.ndarray]] | None = None,
) -> Refinement:
    """The refinement the loop ``grown`` on the records' heads made, its models' parameters
    estimated again on all the ``records``, tails too, as the loop estimated them: the refined
    structure where ``held_out`` kept it, else the start. The declared model by least squares;
    the start by its estimator (its output-error fit searched from least squares, as where nothing
    is added); a structure grown across folds as the folds judged it; any other refined structure
    by output error from the best simulating of its least-squares fit, the parameters the loop
    found and the start's grown by zeros; an output-error fit is kept as
    :func:`_fit_on_all_or_approved` says. The noise floor is read on the whole records, whose
    periods a tail cut off leaves incomplete. ``fitted_ahead``, where given, yields the refined
    structure's least-squares fit on the ``records``, made ahead."""
    result = grown.refinement
    declared_structure = Structure(result.declared.terms)
    declared, _ = fitted_on_all(records, declared_structure)
    everything: Segments = [(x, y, 0) for x, y in records]
    kept = bool(result.effects_added) and (held_out is None or held_out.kept)
    structure = grown.structure if kept else declared_structure
    estimator = result.estimator if kept else grown.start_estimator
    if not kept:
        refined, noise = declared, np.empty(0)
    else:
        ((refined, noise),) = fitted_ahead or [fitted_on_all(records, structure)]
    if estimator == "output error":
        tell("output-error fit on all the records")
        declared_tuned = None
        if not kept or (grown.folded is not None and grown.folded[0] == declared_structure):
            declared_tuned = by_output_error(declared, everything, SETTLED_EVALUATIONS, threads)
        if not kept:
            tuned = declared_tuned
        elif grown.folded is not None:
            before, structures = grown.folded
            tuned = as_the_folds_judged(
                records, before, structures, declared_structure, declared_tuned or declared, threads
            )
        else:
            starts = [refined, replace(refined, theta=result.refined.theta)]
            if grown.start_estimator == "output error":
                starts.append(grown_by_zeros(grown.start, refined))
            start = min(starts, key=lambda model: restless_then_rms(free_run_at_rest(model, records)))
            tuned = by_output_error(start, everything, SETTLED_EVALUATIONS, threads)
        approved = result.refined if kept else grown.start
        chosen = _fit_on_all_or_approved(tuned, refined, approved, records)
        if chosen is None:
            estimator = "least squares"
        else:
            refined = chosen
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


def _fit_on_all_or_approved(
    tuned: NARX | None, least_squares: NARX, approved: NARX, records: Records
) -> NARX | None:
    """The output-error model :func:`_on_all` returns: ``tuned``, the search's fit on all the
    ``records``, where it comes to rest and holds as ``approved``, the fit on the heads
    the tails approved, does (:func:`_holds_as_approved`); where it comes to rest but does not hold
    so, ``approved``, if that comes to rest on all the records (a drift the heads were too short
    to show can show on them); None, least squares' fit on all standing, where the search gained
    nothing over ``least_squares`` or neither holds."""
    if tuned is None or tuned is least_squares or not comes_to_rest(tuned, records):
        return None
    if _holds_as_approved(tuned, approved, records):
        return tuned
    return approved if comes_to_rest(approved, records) else None


def _holds_as_approved(refit: NARX, approved: NARX, records: Records) -> bool:
    """Whether ``refit``, a structure's output-error fit on all the ``records``, may
    stand for ``approved``, the same structure's fit on the heads that the tails approved: it runs
    free over the records no worse, and from no measured output where ``approved`` stays within
    ``RESTLESS`` times the records' largest output does a restart of it leave that range
    (:func:`models.output_error.rings_from_measured`).

    Nothing held out judges the fit on all: the tails judged a procedure on the heads, and the
    same search on more data can end at another optimum. Its free run from each record's start is
    what it lowers; its runs restarted from measured outputs elsewhere it does not see, and a
    numerator that the input hardly drives from rest, with poles that ring long, can set them
    ringing far beyond the records' range (the rig with noise on its y sensor: the linear start's
    fit on all its record rang to twenty times the range, and ran free over a record from another
    seed at six times its spread). ``comes_to_rest`` allows such ringing, which a lightly damped
    mode may do from a noisy state; the approved model is the measure of what the structure may
    ring to. Where the two differ in their lags their restarts are not the same, and the refit
    may ring from none."""
    rings, approved_rings = rings_from_measured(refit, records), rings_from_measured(approved, records)
    allowed = approved_rings if approved_rings.shape == rings.shape else np.zeros_like(rings)
    if np.any(rings & ~allowed):
        return False
    everything: Segments = [(x, y, 0) for x, y in records]
    return free_run_rms(refit, everything) <= free_run_rms(approved, everything)


def _best_tried(kept: Sequence[Round]) -> str | None:
    """The effect whose round lowered the check blocks' free run most, as a share of it."""
    judged = [step for step in kept if step.added is not None and step.check_rms[0] > 0]
    best = min(judged, key=lambda step: step.check_rms[1] / step.check_rms[0], default=None)
    return None if best is None or best.added is None else best.added.name


__all__ = [
    "DEFAULT_ALPHA",
    "MAX_LINEAR_ORDER",
    "MAX_ROUNDS",
    "Comparison",
    "Criterion",
    "Estimator",
    "Refinement",
    "RefinementReport",
    "Round",
    "Stage",
    "Verdict",
    "check_parts",
    "choose_linear",
    "compare",
    "reach",
    "refine",
    "refine_record",
    "refine_records",
]
