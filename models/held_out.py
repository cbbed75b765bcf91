"""The refinement loop's last word: the refined model and its start compared on data that no choice
of the loop saw (SPEC §7, :func:`models.refinement.refine`).

The check blocks choose the effects among many candidates, and a gain chosen as the best of many
is biased upward: a model whose check blocks' free run fell can simulate new data worse than its
start (a polynomial that fits a curve within the estimation data's range and leaves it beyond).
Only data held out from every choice tell whether a gain carries over. The last
``HELD_OUT_SHARE`` of each estimation record is that data: the loop runs on the rest (the heads),
and its refined model is kept only where its free run over the tails is better than the start's
beyond the uncertainty of the comparison (:func:`compare_on_tails`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy

from models.checking import MIN_BLOCK, Segments, free_run_errors, pooled_rms
from models.narx import NARX, run_start, sensor_limits
from models.output_error import diverged
from models.periods import excitation_period
from models.scoring import Records

# The share of each estimation record, at its end, that the loop does not see.
HELD_OUT_SHARE = 0.2
# The fewest samples a tail is held out with: three blocks, the fewest whose spread estimates the
# comparison's uncertainty, each as long as the loop's own shortest check block (a third of the
# shortest record it refines, less the lags: 3·MIN_BLOCK/10 in all). A shorter tail judges the
# effects on less than the loop chose them on. Records of 300 samples.
MIN_TAIL = 3 * MIN_BLOCK // 10
# The level of the comparison, one-sided: one comparison, made once, after every choice. It is
# made two ways (:func:`compare_on_tails`), each at half of it.
HELD_OUT_ALPHA = 0.05
# The tails' errors are cut into at most this many blocks of at least COMPARISON_SAMPLES each:
# enough blocks for the spread of the two models' differences to be estimated, each long enough
# that a free run's correlated errors stay mostly within one.
COMPARISON_BLOCKS = 20
COMPARISON_SAMPLES = 50
# A block's ratio of the two models' mean squares counts for at most this much either way of the
# blocks' median ratio: where one model reproduces a block all but exactly (a clipping sensor's
# plateau), the log ratio of a few such blocks would otherwise swamp the spread of all the others.
# About the median, not about one: a cap about one caps the gain itself, and a model better than
# that on most blocks is then judged as if only that much better, while a block that goes the
# other way keeps its full weight in the spread (:func:`_paired`).
BLOCK_RATIO_CAP = 100.0
# The first samples of each free run over a tail, left out of its blocks: started from the tail's
# measured outputs, both models' free runs sit on them until their errors have built up, over
# about the length these blocks are sized by (a free run's errors change over about that many
# samples). There the two errors measure how well each predicts a few steps ahead, not how it
# simulates, and a block of them can go the other way from every block after it. Left out only
# where the tail keeps three blocks without them; the same samples for both models.
WARM_UP = COMPARISON_SAMPLES


@dataclass(frozen=True)
class HeldOut:
    """The start and the refined model, both fitted on the heads, run free over the held-out
    tails (``samples`` of them, each tail run from its first measured outputs): their free-run
    RMS, the refined model's ``gain`` (the fall of the mean square, as a share of the start's,
    the geometric mean over blocks) and the ``threshold`` it had to exceed, the comparison's
    uncertainty at ``HELD_OUT_ALPHA``. ``diverged``: the refined model's free run diverged there.
    ``kept``: the refined model was returned; otherwise the start was, and ``best_tried`` names
    the effect that had lowered the check blocks' free run most. ``orders_saw_tails``: the linear
    start's orders were chosen on the whole records, tails too (records of a few hundred
    samples, :func:`models.refinement.refine`), which can only favour the start.
    ``kinks_beyond``: the refined model's terms, the start's aside, whose law changes form at an
    output of zero that the records never reached but come near
    (:func:`models.kinks.kinks_beyond_the_records`); where there are any, the refined model is
    not returned, however it ran over the tails. ``set_aside``: the effects of the last rounds
    left out of the refined model, whose free run over the tails with them was ``all_rounds_rms``
    (:mod:`models.rounds_on_tails`)."""

    samples: int
    start_rms: float
    refined_rms: float
    gain: float
    threshold: float
    diverged: bool = False
    kept: bool = True
    best_tried: str | None = None
    orders_saw_tails: bool = False
    kinks_beyond: tuple[str, ...] = ()
    set_aside: tuple[str, ...] = ()
    all_rounds_rms: float = np.nan

    @property
    def better(self) -> bool:
        """Whether the refined model simulates the tails better than the start beyond the
        comparison's uncertainty, and its one free run over them is no worse than the start's.
        The blocks' gain is a geometric mean: a model better on the many quiet blocks, or on pieces
        restarted from measured outputs, can still run free worse over the whole, and that model
        is not the better simulator."""
        return not self.diverged and self.gain > self.threshold and self.refined_rms <= self.start_rms

    @property
    def not_worse(self) -> bool:
        """Whether it simulates them no worse beyond that uncertainty."""
        return not self.diverged and self.gain >= -self.threshold


def unseen_by(orders_saw_tails: bool) -> str:
    """What the report says of the tails' samples: that no choice of the loop saw them, or none
    but the linear orders' (:attr:`HeldOut.orders_saw_tails`)."""
    return "no choice but the linear orders saw" if orders_saw_tails else "no choice saw"


def held_out_tails(records: Records) -> tuple[Records, Segments] | None:
    """The ``records`` without their tails (the heads the loop runs on) and the tails, each with
    its first sample's index in its record; None when a record is too short to hold one out.

    A record whose input repeats (:func:`models.periods.excitation_period`) is cut after a whole
    number of its periods, two at least, the tail at least ``HELD_OUT_SHARE`` of it: the loop
    tells a multisine's own lines and their products from an external tone by the lines of the
    input it is given, which fall on its record's bins only over whole periods, and stand out of
    their neighbours only where a record holds two periods or more (over one period of a
    full-grid multisine every bin is a line).
    """
    cuts = [_cut(x, len(y)) for x, y in records]
    if None in cuts:
        return None
    if any(len(y) - cut < MIN_TAIL for (_, y), cut in zip(records, cuts, strict=True)):
        return None
    heads = [(x[:cut], y[:cut]) for (x, y), cut in zip(records, cuts, strict=True)]
    tails = [(x[cut:], y[cut:], cut) for (x, y), cut in zip(records, cuts, strict=True)]
    return heads, tails


def _cut(x: np.ndarray, n: int) -> int | None:
    """Where a record of ``n`` samples and input ``x`` is cut (:func:`held_out_tails`); None where
    its input repeats and the head cannot hold two of its periods."""
    cut = n - int(n * HELD_OUT_SHARE)
    period = excitation_period(np.asarray(x, dtype=np.float64))
    if period is None:
        return cut
    return cut - cut % period if cut >= 2 * period else None


def compare_on_tails(
    start: NARX,
    refined: NARX,
    tails: Segments,
    alpha: float = HELD_OUT_ALPHA,
    *,
    heads: Records | None = None,
) -> HeldOut:
    """``start`` and ``refined`` compared on the ``tails`` by a paired test over blocks, at level
    ``alpha`` (lower where the tails judge several choices). Each tail continues its
    record's head (:func:`held_out_tails`; ``heads``, where given): a model with memory of the
    signals' past runs it over the measured head, and over the tail's measured part before each
    restarted piece (:func:`models.checking.free_run_errors`).

    The blocks are cut two ways, each tested at half the level (Bonferroni), the refined model
    better where either passes: blocks of one free run over each tail, where a model's error can
    drift until one block holds most of it; and pieces each run from its own measured outputs,
    as the check blocks are, where noise on those outputs starts every piece with a transient that
    blurs the difference. Each block gives d = ln(start's mean square / refined's); under "no
    better" the mean of the K blocks' d over its standard error is Student's t with K − 1 degrees
    of freedom. Log ratios, not differences: a free run's error is heavy-tailed across blocks (a
    few where the excitation is large hold most of it), and a difference of squares is dominated
    by those few. Gain and threshold are reported as shares of the mean square, 1 − exp(−mean d)
    and 1 − exp(−t·SE), from the way that passed (else from the blocks of one free run).
    """
    blocks = comparison_blocks(tails)
    heads = [(x[:0], y[:0]) for x, y, _ in tails] if heads is None else heads
    # Both runs start clear of a sensor's limits where either model has one, so that the blocks
    # pair the same samples (models.narx.run_start).
    limits = sensor_limits(refined) or sensor_limits(start)
    start_errors, refined_errors = (
        free_run_errors(model, tails, heads, limits) for model in (start, refined)
    )
    level = alpha / 2
    comparisons = [
        one_run_comparison(start_errors, refined_errors, level),
        _paired(
            _restarted_squares(start, tails, heads, blocks, limits),
            _restarted_squares(refined, tails, heads, blocks, limits),
            level,
        ),
    ]
    gain, threshold = next((each for each in comparisons if each[0] > each[1]), comparisons[0])
    start_rms, refined_rms = pooled_rms(start_errors), pooled_rms(refined_errors)
    samples = sum(len(y) for _, y, _ in tails)
    return HeldOut(
        samples,
        start_rms,
        refined_rms,
        gain,
        threshold,
        diverged=_diverged(refined, refined_errors, tails, limits),
    )


def _diverged(
    model: NARX, errors: list[np.ndarray], segments: Segments, limits: tuple[float, float] | None
) -> bool:
    """Whether ``model``'s free runs over the ``segments``, whose errors are ``errors``
    (:func:`models.checking.free_run_errors`), diverged as over a test record
    (:func:`models.output_error.diverged`): not finite, or beyond ``RESTLESS`` times the largest
    output measured in their segment. A stable model with a slow mode can ring that far from a
    measured state and stay finite over a tail of a few hundred samples."""
    L = model.max_lag
    measured = [y[run_start(y, L, limits) :] for _, y, _ in segments if len(y) > L]
    return any(diverged(error + y, y) for error, y in zip(errors, measured, strict=True))


def comparison_blocks(segments: Segments) -> int:
    """How many blocks a comparison over ``segments`` cuts their errors into."""
    return _blocks_over(sum(len(y) for _, y, _ in segments))


def _blocks_over(samples: int) -> int:
    """One block for each ``COMPARISON_SAMPLES`` of ``samples``, 3 to ``COMPARISON_BLOCKS``."""
    return int(np.clip(samples // COMPARISON_SAMPLES, 3, COMPARISON_BLOCKS))


def one_run_comparison(
    start_errors: list[np.ndarray], refined_errors: list[np.ndarray], alpha: float
) -> tuple[float, float]:
    """The refined model's gain over the start and its threshold at level ``alpha`` (:func:`_paired`)
    on the blocks of one free run over each tail, whose errors are ``start_errors`` and
    ``refined_errors`` (:func:`models.checking.free_run_errors`, a list over the tails): each
    tail's first ``WARM_UP`` errors left out where at least three blocks' worth stay (the
    same tails for both models, by the longer of their two runs there), the rest cut into one
    block for each ``COMPARISON_SAMPLES`` (3 to ``COMPARISON_BLOCKS``)."""
    enough = WARM_UP + 3 * COMPARISON_SAMPLES
    warm = [max(a.size, b.size) >= enough for a, b in zip(start_errors, refined_errors, strict=True)]
    start_errors, refined_errors = (
        [error[WARM_UP:] if cut else error for error, cut in zip(errors, warm, strict=True)]
        for errors in (start_errors, refined_errors)
    )
    blocks = _blocks_over(sum(error.size for error in start_errors))
    return _paired(_block_squares(start_errors, blocks), _block_squares(refined_errors, blocks), alpha)


def _block_squares(errors: list[np.ndarray], blocks: int) -> np.ndarray:
    """A model's free-run ``errors`` over the segments (:func:`models.checking.free_run_errors`),
    one after the other, cut into ``blocks`` contiguous blocks, each block's mean square; all
    infinite when a run diverges. Where two models' largest lags differ, the few samples the
    longer skips shift the edges a little, alike for both."""
    error = np.concatenate([np.empty(0), *errors])
    if error.size < blocks or not np.all(np.isfinite(error)):
        return np.full(blocks, np.inf)
    return np.array([float(np.mean(part**2)) for part in np.array_split(error, blocks)])


def _restarted_squares(
    model: NARX, segments: Segments, pasts: Records, blocks: int, limits: tuple[float, float] | None
) -> np.ndarray:
    """``segments`` cut into about ``blocks`` pieces (a segment's share by its length), each run
    free from its own first measured outputs, its memory from the measured samples before it
    (the segment's ``pasts`` and the segment up to the piece): ``model``'s mean square over each;
    all infinite when a run diverges. Runs restarted per piece are alike and independent, where
    one long free run's error drifts and a lightly damped model's last blocks can hold nearly
    all of it."""
    total = sum(len(y) for _, y, _ in segments)
    pieces = [
        (
            (x[a : part[-1] + 1], y[a : part[-1] + 1], t0 + a),
            (np.concatenate((past_x, x[:a])), np.concatenate((past_y, y[:a]))),
        )
        for (x, y, t0), (past_x, past_y) in zip(segments, pasts, strict=True)
        for part in np.array_split(np.arange(len(y)), max(1, round(blocks * len(y) / total)))
        for a in (int(part[0]),)
    ]
    squares = np.array(
        [pooled_rms(free_run_errors(model, [piece], [past], limits)) ** 2 for piece, past in pieces]
    )
    return squares if np.all(np.isfinite(squares)) else np.full(squares.size, np.inf)


def _paired(before: np.ndarray, after: np.ndarray, alpha: float) -> tuple[float, float]:
    """The gain of the free run whose block mean squares are ``after`` over ``before``'s and the
    threshold it must exceed at level ``alpha`` (:func:`compare_on_tails`); −∞ and ∞ where the
    second diverged, 1 and 0 where only the first did. Each block's log ratio is held within
    ``ln BLOCK_RATIO_CAP`` of the blocks' median: a cap on the outlying blocks, not on the gain,
    so that a model better on every block by more than the cap is judged by its real gain: a
    further factor on every block raises the mean by its log and leaves the spread as it was."""
    if not np.all(np.isfinite(after)):
        return -np.inf, np.inf
    if not np.all(np.isfinite(before)):
        return 1.0, 0.0
    tiny = np.finfo(np.float64).tiny
    cap = np.log(BLOCK_RATIO_CAP)
    ratio = np.log(np.maximum(before, tiny) / np.maximum(after, tiny))
    typical = float(np.median(ratio))
    # Symmetric under swapping the two models (the median changes sign with every ratio), so that
    # under "equally good" the statistic stays symmetric about zero, as Student's t is.
    ratio = np.clip(ratio, typical - cap, typical + cap)
    error = float(np.std(ratio, ddof=1) / np.sqrt(ratio.size))
    quantile = float(scipy.stats.t.ppf(1 - alpha, ratio.size - 1))
    return float(-np.expm1(-np.mean(ratio))), float(-np.expm1(-quantile * error))
