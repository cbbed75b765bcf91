"""Laws of the output that change form where it crosses zero, in a model whose records never
reach zero but come near it.

A sign, an absolute value or a power law of its magnitude (``sign(y[t-k])``, ``abs(y[t-k])``,
``spow(y[t-k],p)``, ``apow(y[t-k],p)``) is a law anchored at the output's zero: on one side of
it the term is one smooth curve, on the other its mirror (odd or even), and the two meet in a
kink. Fitted on records whose outputs stay on one side of zero, it is only a curve over their
range, as a polynomial would be; what it does across zero is the law's assumption, and no record
judged it. A polynomial's continuation beyond the range is the analytic one its coefficients
fix; a kinked law's continuation across its kink is not fixed by anything on one side of it
(Billings 2013, ch. 14: a model is valid over the range its data covered).

A law fitted on one side of zero can stand in there for an even one (a signed power law for a
square, say): across zero the model then mirrors what it learnt, a restoring force or a well the
system does not have, and a record that crosses zero finds the model there.

Zero matters where a record of the same structure reaches it: within as far again beyond the
records' range as that range is wide, as a somewhat stronger force, or a record that wanders a
little further, takes it. Further away, the law near the records is a smooth curve whose kink no
record of this kind reaches.

The loop does not offer such a law on such records either (:func:`offered_within_the_records`):
a model holding one is refused whatever the tails say, so a round that adds it commits the
refinement to a model that will not be returned, where a polynomial, its analytic equal over the
records, would have taken the round.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.effects import Effect, reads_magnitude
from models.narx import NARX
from models.scoring import Records
from models.terms import POWER_LAWS, Term

# The functions of a signal whose law changes form where it crosses zero.
KINKED = ("abs", "sign", *POWER_LAWS)


def kinked_laws_reason(terms: Sequence[str]) -> str:
    """Why a refined model holding the kinked laws ``terms`` is not returned, in one phrase that
    the report and the command line share."""
    return (
        f"the refined model's {', '.join(terms)} change form at an output of zero the records come "
        "near but never reach"
    )


def kinked_at_zero(term: Term) -> bool:
    """Whether ``term`` holds a factor of the output whose law changes form at zero (``KINKED``).
    Differences of the output (velocities) cross zero on every record, and are left out."""
    return any(factor.signal == "y" and factor.function in KINKED for factor in term.factors)


def kinks_beyond_the_records(start: NARX, refined: NARX, records: Records) -> tuple[str, ...]:
    """The terms of ``refined`` that ``start`` lacks and that change form where the output
    crosses zero (:func:`kinked_at_zero`), where the ``records``' outputs stay on one side of
    zero and come within as far again as their range is wide of it; empty otherwise. A rectified
    model's recursion runs on a signed output whose zero the readings come down to, and is
    passed over."""
    if refined.rectified or not near_an_unreached_zero(records):
        return ()
    own = set(start.terms)
    return tuple(term.name for term in refined.terms if term not in own and kinked_at_zero(term))


def near_an_unreached_zero(records: Records) -> bool:
    """Whether the ``records``' outputs stay on one side of zero and come within as far again as
    their range is wide of it."""
    low = min(float(min(y)) for _, y in records)
    high = max(float(max(y)) for _, y in records)
    if low <= 0.0 <= high or not high > low:
        return False
    return min(abs(low), abs(high)) <= high - low


def offered_within_the_records(families: Sequence[Effect], records: Records) -> list[Effect]:
    """The ``families`` a loop on the ``records`` offers: those whose terms are a law of the output
    kinked at zero (:func:`kinked_at_zero`, or ``Effect.kinked_law`` for a law found from the
    residual) left out where the records come near a zero they never reach
    (:func:`near_an_unreached_zero`), since :func:`kinks_beyond_the_records` would refuse a model
    that holds one. Records that read as a magnitude keep them: their model may be rectified, its
    recursion on a signed output, and that model's laws are passed over there too."""
    if not near_an_unreached_zero(records) or reads_magnitude(np.concatenate([y for _, y in records])):
        return list(families)
    return [
        family
        for family in families
        if not (family.kinked_law or any(kinked_at_zero(term) for term in family.terms))
    ]
