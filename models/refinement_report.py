"""What the refinement loop (:mod:`models.refinement`) returns and reports: each round
(:class:`Round`), the refinement (:class:`Refinement`), the declared and refined models judged on
held-out data (:class:`Comparison`, :class:`RefinementReport`), and the report as JSON with the
notes it makes in words. Also the loop's vocabulary its phases share: how a family was decided
(:data:`Criterion`), how parameters were estimated (:data:`Estimator`) and the stages told as
the loop goes (:data:`Stage`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from models.amplitude_range import AmplitudeRanges
from models.assessment import Assessment
from models.coverage import Coverage
from models.held_out import HELD_OUT_ALPHA, HeldOut, unseen_by
from models.kinks import kinked_laws_reason
from models.narx import NARX
from models.periods import PeriodNoise
from models.scoring import EffectScore

# Told each stage of the loop as it begins, in words ("round 2: scoring 17 families"): a loop on
# long records runs for minutes, and a caller shows where it is.
Stage = Callable[[str], None]
Criterion = Literal[
    "one-step", "output error", "simulation", "simulation across folds", "output's range", "pair", "whiteness"
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
    ``SIMULATION_GAIN``; a state of the output, by that share beyond the one-step criterion's
    choice: :func:`models.round_criteria.output_state_by_simulation`), "simulation across
    folds" (its settled output-error model lowered the free run over the checked records of each
    of three folds by at least ``FOLD_GAIN``),
    "output's range" (the rectifier, taken where the records read as a magnitude) or "pair" (the
    first significant family, whose model alone ran free worse, with the family the next round
    adds lowering that free run by at least ``SIMULATION_GAIN``: :func:`models.round_criteria.as_pair`)
    or "whiteness" (moving-average noise after the rounds, its lags significant on the returned
    model's one-step residual, the process left as it was: :mod:`models.noise_model`);
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
    # The terms pruned after the rounds, in the order taken out (:func:`models.pruning.pruned_back`),
    # on the last round; ``check_rms`` is then after the pruning.
    pruned: tuple[str, ...] = ()
    # The effect added here (the generic polynomial) pruned whole after the rounds: a later
    # round's effect made it redundant, and the refined model holds none of its terms.
    pruned_whole: bool = False
    # The effect added here left out of the model returned, with every later round's: the model the
    # rounds before it grew ran free over the held-out tails better (:mod:`models.rounds_on_tails`).
    set_aside: bool = False
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
    check took back every effect the first ``withdrawn`` rounds added (:mod:`models.refinement`); the
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
    # settled (:func:`models.settling.settled_from`); empty where none were.
    settled_from: tuple[int, ...] = ()

    @property
    def kept(self) -> tuple[Round, ...]:
        """The rounds whose effect the refined model holds."""
        return tuple(
            r
            for r in self.rounds[self.withdrawn :]
            if r.added is not None and not r.pruned_whole and not r.set_aside
        )

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
    holds one comparison a test record; ``before``/``after`` are the first one's.
    ``amplitude_range`` holds both models' amplitude ranges over the estimation records
    (:mod:`models.amplitude_range`): where the refined model's is the narrower, the report says so,
    and the loop returns it all the same."""

    refinement: Refinement
    tests: tuple[Comparison, ...]
    notes: tuple[str, ...] = ()
    amplitude_range: AmplitudeRanges | None = None

    @property
    def before(self) -> Assessment:
        return self.tests[0].before

    @property
    def after(self) -> Assessment:
        return self.tests[0].after

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: effects added in order with their evidence and the criterion that
        decided each, errors before and after on every test record, and both models' terms and
        parameters. Non-finite numbers (a diverged free run) become None. ``amplitude_range``
        gives each model's as ``bounded_to`` (the largest scale of the estimation inputs up to
        which its free run stayed bounded; None: no limit) and ``diverges_at`` (the first scale
        at which it diverged; None: none of the scales tried); each test's
        ``beyond_amplitude_range`` says, where the refined model diverged on it and its input
        reaches beyond that range, why."""
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
                    "set_aside": step.set_aside,
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
                    | {
                        "input_scale": _finite(test.coverage.input_scale),
                        "extrapolates": test.coverage.extrapolates,
                        "description": test.coverage.describe(),
                    },
                    "verdict": test.verdict,
                    "beyond_amplitude_range": _beyond_amplitude_range(test, self.amplitude_range),
                }
                for test in self.tests
            ],
            "refined": _model_dict(result.refined)
            | {"noise_ma": result.noise.tolist(), "estimator": result.estimator},
            "settled_from": list(result.settled_from),
            "amplitude_range": None if self.amplitude_range is None else self.amplitude_range.to_dict(),
            "notes": list(self.notes)
            + held_out_notes(result)
            + _range_notes(self.amplitude_range, result)
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
        "kinks_beyond": list(held_out.kinks_beyond),
        "set_aside": list(held_out.set_aside),
        "all_rounds_free_run_rms": _finite(held_out.all_rounds_rms),
    }


def held_out_notes(result: Refinement) -> list[str]:
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
        if not held_out.set_aside:
            return []
        return [
            f"over the estimation records' held-out tails the model with the last rounds' effects "
            f"({', '.join(held_out.set_aside)}) ran free at {held_out.all_rounds_rms:.4g}, the model "
            f"of the rounds before them at {held_out.refined_rms:.4g}: those effects are set aside"
        ]
    if held_out.kinks_beyond:
        return [
            f"the data could not support the effects: {kinked_laws_reason(held_out.kinks_beyond)}; "
            "across zero those laws mirror themselves as no record showed, and a record that crosses "
            f"it would find the model there. The start is returned (the best effect tried: "
            f"{held_out.best_tried})"
        ]
    refined = "diverged" if held_out.diverged else f"ran free at {held_out.refined_rms:.4g}"
    return [
        f"the data could not support the effects: over the estimation records' held-out tails "
        f"({held_out.samples} samples {unseen_by(held_out.orders_saw_tails)}) the refined model "
        f"{refined} against the start's "
        f"{held_out.start_rms:.4g}, not better beyond the comparison's uncertainty; the start is "
        f"returned (the best effect tried: {held_out.best_tried})"
    ]


def _range_notes(ranges: AmplitudeRanges | None, result: Refinement) -> list[str]:
    """What the report says where the refined model diverges at an amplitude of the estimation
    inputs that the declared model (or the linear start) runs bounded at."""
    if ranges is None or not ranges.narrower:
        return []
    start = "the linear start" if result.orders is not None else "the declared model"
    refined, declared = ranges.refined, ranges.declared
    if refined.bounded_to == 0.0:
        said = "the refined model diverges over the estimation records' inputs themselves"
    else:
        said = (
            f"the refined model is bounded for inputs up to {refined.bounded_to:g}× the estimation "
            "records' amplitude; beyond that it diverges"
        )
    if not declared.limited:
        said += f", {start} does not"
    else:
        said += f", {start} only from {declared.diverges_at:g}× on"
    return [
        f"{said}: judge the refined model on records within that range (a model with a hardening "
        "spring's cube has a finite range too; the loop does not refuse it for that)"
    ]


def _beyond_amplitude_range(test: Comparison, ranges: AmplitudeRanges | None) -> str | None:
    """Why the refined model diverged on a test record, where the record's input reaches beyond
    the refined model's amplitude range and the record extrapolates; None otherwise."""
    if ranges is None or test.verdict != "diverged" or not test.coverage.extrapolates:
        return None
    refined = ranges.refined
    if test.coverage.input_scale <= refined.bounded_to:
        return None
    return (
        f"its input reaches {test.coverage.input_scale:.2g}× the estimation records' largest, beyond "
        f"the refined model's amplitude range: {refined.describe()}"
    )


def _skipped_notes(tests: Sequence[Comparison]) -> list[str]:
    """A note for each test record too short for the residual tests, naming those skipped."""
    return [
        f"test record {number} is too short for the residual tests ({', '.join(test.after.skipped)}): "
        "skipped; its free-run and one-step errors are scored"
        for number, test in enumerate(tests, start=1)
        if test.after.skipped
    ]


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


def told(progress: Stage | None) -> Stage:
    """``progress``, or a stage that tells no one."""
    return progress if progress is not None else lambda stage: None


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None


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
