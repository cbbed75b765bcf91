"""The refinement protocol that ``narxwatch refine`` and the API's refinements share: the loop
(:mod:`models.refinement`) run on parts of one record or on whole records, both models judged,
the effects added explained on the first record judged (:mod:`models.explanation`), and the
report's document with each record judged named as its caller names it.

**Parts of one record**: the loop fits the estimation parts (by default the first two thirds;
several parts are fitted as records of their own) and both models are judged on the test part
(by default the last third), then on each validation record whole. **Whole records**: the loop
fits all the estimation records at once and both models are judged on each test record whole,
run through its first ``transient`` samples and scored after them.

The callers keep what is theirs: reading the records and naming them (files, stored records),
the options or the request, and what they print or store.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from models.explanation import Explanation, explain_refinement
from models.refinement import (
    DEFAULT_ALPHA,
    RefinementReport,
    Stage,
    compare,
    refine_record,
    refine_records,
)
from models.regression import Workers
from models.scoring import Records
from models.terms import Term


@dataclass(frozen=True)
class Loop:
    """What the loop runs with on either protocol: the declared terms (None: the loop chooses a
    linear model's orders), the measured samples each test run starts from, the family-wise
    level of each round, the sampling rate, and the samples at the start of each record judged
    whole that hold its transient (run through, not scored); ``progress``, ``workers`` and
    ``threads`` as for :func:`models.refinement.refine`."""

    declared: Sequence[str | Term] | None
    initial: int = 0
    alpha: float = DEFAULT_ALPHA
    fs: float | None = None
    transient: int = 0
    progress: Stage | None = None
    workers: Workers = map
    threads: Workers = map


@dataclass(frozen=True)
class Refined:
    """A refinement's report, its explanation, and the record it was explained on: the first
    judged (on parts of one record, its test part)."""

    report: RefinementReport
    explanation: Explanation
    explained: tuple[np.ndarray, np.ndarray]

    def to_dict(self, judged: Sequence[dict[str, Any]]) -> dict[str, Any]:
        """The report's document (:meth:`RefinementReport.to_dict`) with the explanation in it,
        each test merged with ``judged``'s entry for it: where the caller says it comes from."""
        document = self.report.to_dict()
        self.explanation.into(document)
        document["tests"] = [where | item for where, item in zip(judged, document["tests"], strict=True)]
        return document


def default_split(n: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """A record of ``n`` samples' estimation and test parts where none are given: the first two
    thirds fit, the last third judges."""
    return (0, 2 * n // 3), (2 * n // 3, n)


def refine_parts(
    loop: Loop,
    x: np.ndarray,
    y: np.ndarray,
    estimation: Sequence[tuple[int, int]],
    test: tuple[int, int],
    validation: Records = (),
    names: Sequence[str] = (),
) -> Refined:
    """The loop on the ``estimation`` parts of one record, both models judged on its ``test``
    part (:func:`models.refinement.refine_record`), then on each ``validation`` record whole,
    without refitting: run from the record's start, and scored after its transient. ``names``
    are how ``progress`` calls the validation records."""
    report = refine_record(
        x,
        y,
        loop.declared,
        estimation,
        test,
        loop.initial,
        loop.alpha,
        loop.fs,
        progress=loop.progress,
        workers=loop.workers,
        threads=loop.threads,
    )
    fitted = [(x[a:b], y[a:b]) for a, b in estimation]
    judged = []
    for name, (x_whole, y_whole) in zip(names, validation, strict=True):
        if loop.progress is not None:
            loop.progress(f"judging both models on {name}")
        judged.append(
            compare(report.refinement, fitted, x_whole, y_whole, loop.initial, loop.fs, 0, loop.transient)
        )
    report = replace(report, tests=report.tests + tuple(judged))
    c, d = test
    explained = (x[c:d], y[c:d])
    # The test part's time counts from the first estimation part's start, as the loop judged it.
    explanation = explain_refinement(report.refinement, *explained, loop.initial, c - estimation[0][0])
    return Refined(report, explanation, explained)


def refine_whole(
    loop: Loop, estimation: Records, tests: Records, names: Sequence[str] | None = None
) -> Refined:
    """The loop on whole ``estimation`` records, fitted through their transient, both models
    judged on each of ``tests`` whole, run from its start and scored after its transient
    (:func:`models.refinement.refine_records`; ``names`` are how its notes call the estimation
    records)."""
    report = refine_records(
        estimation,
        tests,
        loop.declared,
        loop.initial,
        loop.alpha,
        loop.fs,
        loop.transient,
        progress=loop.progress,
        workers=loop.workers,
        threads=loop.threads,
        names=names,
    )
    explained = tests[0]
    explanation = explain_refinement(report.refinement, *explained, loop.initial, 0, loop.transient)
    return Refined(report, explanation, explained)
