"""A model's fixed points: the outputs it comes to rest at with its input held at a constant level,
and whether the refined model claims any beyond the outputs its records measured.

A NARX model's fixed points (its static characteristic, Aguirre & Billings 1995; Billings 2013,
ch. 5) are the levels v at which y[t] = v is a solution of its recursion when every lagged output
is v and every lagged input the same constant: every difference is zero, a sinusoid of time
averages out and a Bouc–Wen variable rests at zero. They are where the model settles, and which
way it moves from a level between them, so they say how it behaves beyond the records' range,
where no free run over them looks.

A polynomial or a power law fitted over a range of outputs is valid over that range; beyond it
nothing in the records constrains it (Billings 2013, ch. 14: model validity and extrapolation).
Where the records stay on one side of a point, an odd law (a cube, a signed power) and an even one
(a square) fit them alike and mirror each other across it: on the rig with a quadratic spring,
whose record stayed in the well the spring makes at −0.3 m, the loop's cube and signed power of
the output, nothing declared, put an unstable fixed point at 0 and a stable one at +0.3 m where
the system rests at 0; over a record from another seed that left the well, the model fell into
the one it had made and stayed there, running free several times as far off as its linear start.
A fixed point within the records' range is a state they visited and judged; one beyond it is a
claim none of them bears on.
"""

from __future__ import annotations

import numpy as np

from models.narx import NARX
from models.scoring import Records
from models.terms import OUTPUT_HYSTERESES, WAVES, Factor

# Levels of the output a model's static characteristic is evaluated at over the span it is
# searched on: fixed points closer together than a span over this many are not told apart.
LEVELS = 2001


def fixed_points(model: NARX, input_level: float, low: float, high: float) -> np.ndarray:
    """The levels v in [low, high] at which ``model``, its lagged outputs all v and its lagged
    inputs all ``input_level``, predicts v: where its static characteristic f(v) − v changes
    sign between two of ``LEVELS`` levels (the midpoint of the two)."""
    levels = np.linspace(low, high, LEVELS)
    inputs = np.full(LEVELS, input_level)
    columns = [
        np.prod([_at_rest(factor, levels, inputs) for factor in term.factors], axis=0) for term in model.terms
    ]
    predicted = np.column_stack([np.broadcast_to(column, levels.shape) for column in columns]) @ model.theta
    if model.rectified:
        predicted = np.abs(predicted)
    if model.output_limits is not None:
        predicted = np.clip(predicted, *model.output_limits)
    # A level where f(v) − v is exactly zero is passed over: the change of sign about it is found
    # between its neighbours.
    sign = np.sign(predicted - levels)
    nonzero = np.flatnonzero(sign)
    before, after = nonzero[:-1], nonzero[1:]
    changes = sign[before] != sign[after]
    return (levels[before[changes]] + levels[after[changes]]) / 2


def _at_rest(factor: Factor, levels: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """``factor`` where the output has rested at each of ``levels`` and the input at ``inputs``:
    differences zero; a sinusoid of time, which averages out, and a Bouc–Wen variable, whose rest
    depends on the path that led there, zero."""
    if factor.signal in WAVES or factor.function in OUTPUT_HYSTERESES:
        return np.zeros_like(levels)
    return factor.values(lambda _: levels, lambda _: inputs, np.zeros_like(levels))


def beyond_the_records(start: NARX, refined: NARX, records: Records) -> tuple[float, ...]:
    """The ``refined`` model's fixed points outside the range of the outputs the ``records``
    measured, within as far again as that range is wide on either side, where it has more there
    than ``start``; empty where it has none so. The input is held at the records' mean.

    As far again as the range is wide: a record of the same structure under a somewhat stronger
    force, or one that wanders a little further than the estimation records did, reaches there,
    and a model that settles, or turns away, at a level the records never showed misleads every
    judgement of such a record; further away a fixed point is a claim about forces no record of
    this kind will apply. More than the start: a declared start's own fixed points are the
    declaration's, not the loop's."""
    outputs = np.concatenate([np.asarray(y, dtype=np.float64) for _, y in records])
    inputs = np.concatenate([np.asarray(x, dtype=np.float64) for x, _ in records])
    low, high = float(np.min(outputs)), float(np.max(outputs))
    width = high - low
    if not width > 0:
        return ()
    level = float(np.mean(inputs))

    def outside(model: NARX) -> np.ndarray:
        found = fixed_points(model, level, low - width, high + width)
        return found[(found < low) | (found > high)]

    claimed = outside(refined)
    return tuple(float(point) for point in claimed) if claimed.size > outside(start).size else ()
