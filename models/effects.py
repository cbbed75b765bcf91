"""Candidate effects: the named physical effects a NARX model may lack, as families of regressors.

Each family is sized to the model it would extend. The lags span those of the model (at least
1 … 4 for y): an effect entering the physics on an unmeasured mass reaches the measured
response through the same dynamics, at those lags. Velocities enter as first differences of
the response, dy[t-k] = y[t-k] − y[t-k-1].

Beyond the forces on the measured coordinate, the families name effects on the output side and
behind the sensor:

- output saturation: plateaus at the record's extremes (an overflowing tank, a clipping
  sensor); the model gains output limits (:func:`output_limits`), of its state or of its sensor,
  that its predictions and free run are clipped to (:mod:`models.narx`);
- a rectified output: a sensor blind to the sign of what it measures (a pulse counter on a shaft
  turning either way), offered where the output never goes below zero and comes down to it
  (:func:`reads_magnitude`); the model's recursion runs on a signed output z and reports |z|
  (:mod:`models.narx`);
- power laws |y|^p·sign y and |dy|^p·sign dy with p estimated (outflow through an orifice
  ∝ √level, turbulent or aerodynamic damping);
- an input dead zone or backlash of a width estimated from the data;
- hysteresis through a Bouc–Wen variable of the output: Bouc and Wen's
  dz = A·dx − β|dx|·z − γ·dx·|z| (Wen 1976; Ikhouane & Rodellar, *Systems with Hysteresis*,
  2007, ch. 2) with n = 1 and A = 1, advanced exactly over each step of y
  (:func:`models.terms.bouc_wen_step`); its level 1/(2β) and shape γ/β are estimated
  together (:func:`hysteresis_terms`);
- a nonlinear spring on a degree of freedom the sensor does not measure: its coordinate is a
  linear combination of the measured one's lags, so its force is the cube of that combination,
  fitted to the residual as one regressor (:func:`unmeasured_cube`) and added as the cross-lag
  cubics that span it;
- dynamics the input modulates (a bilinear system): products x[t-j]·y[t-i], the input scaling
  the output's own terms, as a drive switching a motor/generator's circuit changes its damping;
- a static nonlinearity between two linear filters (Wiener–Hammerstein), y = G2(f(G1 x)):
  G1 x is a combination u[t] = Σ_k c_k·x[t-k] of the input's lags, so f's square and cube are
  a·u² + b·u³, fitted to the residual as one regressor (:func:`filtered_input_powers`) and added
  as the monomials of degree 2 and 3 of x's lags that span it. Both combinations are found by
  one search (:func:`combination_terms`).

Parameters estimated from the data (an exponent, a width) are found like a periodic
disturbance's frequencies: from the residual, by a profile search (:func:`profile_search`)
of how much of it the family explains.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import scipy
from scipy import linalg

from models.errors import InputError
from models.regression import column_norms, divided_columns, orthogonal_part
from models.spectrum import excited_intervals, residual_spectrum
from models.terms import WAVES, Factor, Term, bouc_wen, regressor_matrix

EffectKind = Literal[
    "terms", "output_shift", "periodic", "noise", "estimated", "saturation", "rectified", "combined"
]
# What an "estimated" effect is: given what its parameters are sought from (:class:`SearchInput`),
# the family's terms with their parameters estimated.
Finder = Callable[["SearchInput"], tuple[Term, ...]]
# What a "combined" effect is: given the records (x, y pairs), the residual over their stacked rows
# lag … N−1, the model's terms and lag, the terms that span its one regressor beside the model's,
# and that regressor over the same rows.
Combiner = Callable[
    [Sequence[tuple[np.ndarray, np.ndarray]], np.ndarray, Sequence[Term], int],
    tuple[tuple[Term, ...], np.ndarray],
]
# A plateau is at least this many consecutive samples at the record's maximum (or minimum):
# a smooth signal visits its extreme once.
PLATEAU_SAMPLES = 3
# A rectified output's readings may lie below zero, or stay above it, by this share of their range:
# a sensor's offset at rest (the coupled drives' pulse counter reads −0.022 at rest, 1 % of it).
MAGNITUDE_SLACK = 0.02
# The offset family, by name: its form follows the model's (:func:`offset_effect`).
OFFSET = "offset"
OFFSET_DESCRIPTION = "constant offset: sensor bias or static load"
# The rectified-output family's one regressor, by name: it adds no term.
RECTIFIED = "rectified"
# Exponents of the power laws, clear of the integer laws named by their own families (Coulomb
# friction at 0, quadratic damping at 2, cubic stiffness and damping at 3) and of the linear 1.
STIFFNESS_EXPONENTS = (0.2, 2.6)
DAMPING_EXPONENTS = (0.2, 1.8)
# The integer laws of each power law's signal that a family names, by exponent: where one of these
# explains the residual better than the law at its fitted exponent, beyond that exponent's
# uncertainty, the effect is that family's (:func:`power_law_terms`).
STIFFNESS_LAWS = (("cubic_stiffness", 3.0),)
DAMPING_LAWS = (("coulomb_friction", 0.0), ("quadratic_damping", 2.0), ("cubic_damping", 3.0))
# The level at which an integer law is told from a fitted exponent (a likelihood-ratio test of one
# degree of freedom, :func:`integer_law_better`): the families' tests' level.
EXPONENT_ALPHA = 0.01
PROFILE_POINTS = 12
# Rows a parameter search reads (the first ones): plenty to fix one parameter, or a few, to the
# digits a term's name keeps, and a long record's search stays as quick as a short one's.
SEARCH_ROWS = 10_000
# Starting directions of the search for a combination of lags (an unmeasured coordinate, a filtered
# input): sign patterns of equal weights. On the 2-DOF rig the search for the unmeasured coordinate
# converges from half of the first eight; four keep it quick.
COMBINATION_STARTS = 4
# The powers of a combination of lags each combined family fits: a filtered input's square and cube
# (:func:`filtered_input_powers`), an unmeasured coordinate's cube (:func:`unmeasured_cube`).
FILTERED_POWERS = (2, 3)
UNMEASURED_POWERS = (3,)
# The generic family (:func:`polynomial_effect`): its name, which the loop offers after every named
# family, and the shortest lags of y and of x whose products it holds (and the bilinear family,
# :func:`bilinear_effect`).
POLYNOMIAL = "polynomial"
POLYNOMIAL_LAGS = 3
# The hysteresis family: its Bouc–Wen variable is a state of the output, which the one-step test
# reads beside the residual's own past (:func:`models.round_criteria.output_state_by_simulation`).
HYSTERESIS = "hysteresis"
# The grid of the Bouc–Wen shape r = γ/β (first, last, points), 1 (β = γ) among them. It spans
# Ikhouane and Rodellar's classes of the n = 1 loop: r in (−1, 1] bounded, stiffer on unloading
# than on loading (the classical loop); r > 1 bounded, softer on unloading too; r < −1 unbounded,
# stiffening as the output moves on from where it turned.
BOUC_WEN_SHAPES = (-3.0, 3.0, 7)


@dataclass(frozen=True)
class SearchInput:
    """What an "estimated" family's parameters are sought from, a :data:`Finder`'s argument: the
    record (x, y), the model's residual over its rows lag … N−1, the model's terms and its lag.
    One object, since every family's search reads all five and hands them on as they are."""

    x: np.ndarray
    y: np.ndarray
    residual: np.ndarray
    terms: Sequence[Term]
    lag: int


@dataclass(frozen=True)
class Effect:
    """A named effect and the regressors that represent it.

    ``kind`` says how the effect is tested against a residual:

    - "terms": its terms' regressors, entering one by one while significant;
    - "output_shift": one regressor, the direction in which an offset of the measured output
      moves the model's prediction (:func:`offset_direction`); adding it adds ``terms``, the
      monomials that offset brings into the model;
    - "periodic": a sine and a cosine at each significant peak of the residual spectrum that
      the input does not excite (:func:`periodic_terms`); its ``terms`` are found from the
      residual, so empty here;
    - "noise": moving-average terms e[t-k] of the residual itself, which make the model a
      NARMAX estimated by extended least squares (:mod:`models.narmax`); no terms either;
    - "estimated": terms with a parameter estimated from the data, found by ``find`` (a
      :data:`Finder`) from the residual; no terms here;
    - "saturation": one regressor, the change clipping the prediction to the record's plateaus
      makes (:func:`saturation_direction`); adding it gives the model output limits, no terms;
    - "rectified": one regressor, the change reading the magnitude of the prediction makes
      (:func:`magnitude_direction`), where the output reads as a magnitude
      (:func:`reads_magnitude`); adding it makes the model ``rectified``, no terms;
    - "combined": one regressor, a nonlinear function of a combination of the data's lags fitted
      to the residual by ``combine`` (a :data:`Combiner`) whose expansion its ``terms`` span;
      adding it adds them.
    """

    name: str
    description: str
    terms: tuple[Term, ...]
    kind: EffectKind = "terms"
    find: Finder | None = field(default=None, compare=False)
    combine: Combiner | None = field(default=None, compare=False)
    # For a law whose exponent is searched: the families naming an integer law of its signal, by
    # exponent, which a law at an exponent between it and the linear law can blend with an effect
    # beside them (:func:`models.round_criteria.integer_law_first`).
    integer_laws: tuple[tuple[str, float], ...] = ()
    # Parameters its search fits to the residual its test then reads (an exponent; a combination's
    # direction and the ratio of its powers), counted among the parameters of its first entry's
    # test (:func:`models.scoring.score_columns`): chosen to explain that residual best, they
    # would otherwise pass as free.
    searched: int = 0
    # For a family whose terms are found from the residual: they will be a law of the output that
    # changes form where it crosses zero (:mod:`models.kinks`), known before the search.
    kinked_law: bool = False
    # For a combined family: the effect's own evidence comes first, a column of its own (an
    # offset's constant), and only where that is not significant is the combination tested, what
    # the effect shows through where its own evidence is hidden (:func:`offset_effect`).
    evidence_first: bool = False

    @property
    def regressors(self) -> int:
        """How many regressors testing the effect puts beside the model's before its data are
        seen: one for a shift, a saturation or a combination (whatever terms span them), the
        terms' count otherwise (none yet for families found from the residual)."""
        return 1 if self.kind in ("output_shift", "saturation", "rectified", "combined") else len(self.terms)


# Coloured noise: the moving-average terms of a NARMAX, offered in the rounds and, after them, as
# the refined model's noise model (:mod:`models.noise_model`).
MOVING_AVERAGE_NOISE = Effect(
    "moving_average_noise", "coloured noise: moving-average terms e[t-k] (NARMAX)", (), "noise"
)


def linear_terms(ny: int, nx: int, delay: int = 1, constant: bool = False) -> tuple[Term, ...]:
    """A linear ARX structure: y[t-1] … y[t-ny] and x[t-delay] … x[t-delay-nx+1], and with a
    ``constant`` the term 1 (an operating point away from zero)."""
    if ny < 1 or nx < 1 or delay < 0:
        raise InputError(
            f"a linear ARX structure needs ny >= 1, nx >= 1, delay >= 0; got {ny}, {nx}, {delay}"
        )
    ys = [Term((Factor("y", lag),)) for lag in range(1, ny + 1)]
    xs = [Term((Factor("x", lag),)) for lag in range(delay, delay + nx)]
    return tuple(ys + xs + ([Term()] if constant else []))


def candidate_effects(terms: Sequence[Term]) -> list[Effect]:
    """The effect families a model with these terms may lack; terms it has are left out."""
    y_lags = [f.lag for t in terms for f in t.factors if f.signal == "y"]
    x_lags = sorted({f.lag for t in terms for f in t.factors if f.signal == "x"}) or [1]
    ny = max(y_lags, default=0)
    lags_y = range(1, max(ny, 4) + 1)
    effects = [
        *_force_effects(lags_y),
        *_input_effects(x_lags),
        bilinear_effect(terms),
        *_estimated_effects(lags_y, x_lags),
        *_structure_effects(terms, ny, x_lags),
    ]
    return unused(effects, terms)


def _powers(signal: str, lags: Sequence[int], power: int) -> tuple[Term, ...]:
    """The terms signal[t-k]^power, one for each lag k."""
    return tuple(Term((Factor(signal, lag, power),)) for lag in lags)


def _force_effects(lags_y: Sequence[int]) -> list[Effect]:
    """The restoring and damping forces on the measured coordinate, of y and of its velocity dy."""
    velocity = [Factor("dy", lag) for lag in lags_y]
    return [
        Effect("cubic_stiffness", "cubic restoring force: a stiffening spring", _powers("y", lags_y, 3)),
        Effect(
            "quadratic_stiffness", "quadratic restoring force: an asymmetric spring", _powers("y", lags_y, 2)
        ),
        Effect(
            "coulomb_friction",
            "dry friction: a force of constant size against the velocity, sign(dy)",
            tuple(Term((Factor("dy", v.lag, function="sign"),)) for v in velocity),
        ),
        Effect(
            "quadratic_damping",
            "quadratic damping: a force growing with the velocity squared, dy·|dy|",
            tuple(Term.of([v, Factor("dy", v.lag, function="abs")]) for v in velocity),
        ),
        Effect(
            "cubic_damping",
            "cubic damping: a force growing with the velocity cubed, dy³",
            tuple(Term((Factor("dy", v.lag, 3),)) for v in velocity),
        ),
    ]


def _input_effects(x_lags: Sequence[int]) -> list[Effect]:
    """The nonlinearities of the excitation path: of x's lags, or of a filtered combination of them."""
    input_nonlinearity = Effect(
        "input_nonlinearity",
        "nonlinear excitation path: actuator or amplifier, x² and x³",
        _powers("x", x_lags, 2) + _powers("x", x_lags, 3),
    )
    # A combination of one lag is the input nonlinearity's own x², x³: the family needs two.
    if len(x_lags) == 1:
        return [input_nonlinearity]
    filtered_terms = tuple(
        Term.of(product)
        for degree in FILTERED_POWERS
        for product in itertools.combinations_with_replacement([Factor("x", k) for k in x_lags], degree)
    )
    filtered = Effect(
        "filtered_input_nonlinearity",
        "a static nonlinearity between two linear filters (Wiener–Hammerstein): the square "
        "and cube of a combination of x's lags, as the monomials of degree 2 and 3 of x's lags",
        filtered_terms,
        "combined",
        combine=filtered_input_powers(x_lags, filtered_terms),
        searched=combination_parameters(x_lags, FILTERED_POWERS),
    )
    return [input_nonlinearity, filtered]


def _estimated_effects(lags_y: Sequence[int], x_lags: Sequence[int]) -> list[Effect]:
    """The families whose terms are found from the residual: a parameter estimated (a level, an
    exponent, a width) or a combination of lags fitted."""
    cube_terms = tuple(
        Term.of(product)
        for product in itertools.combinations_with_replacement(
            [Factor("y", lags_y[-1])] + [Factor("dy", k) for k in lags_y[:-1]], 3
        )
    )
    return [
        Effect(
            HYSTERESIS,
            "a hysteretic restoring force (Bouc–Wen): the hysteretic variable z of y, its level and "
            "shape estimated",
            (),
            "estimated",
            functools.partial(hysteresis_terms, lags_y),
        ),
        Effect(
            "unmeasured_nonlinearity",
            "a nonlinear spring on a coordinate y does not measure, reaching y through the linear "
            "dynamics: the cube of a combination of y's lags, as cubics of y[t-m] and dy[t-k]",
            cube_terms,
            "combined",
            combine=unmeasured_cube(cube_terms),
            searched=combination_parameters(lags_y, UNMEASURED_POWERS),
        ),
        Effect(
            "power_law_stiffness",
            "a restoring force or outflow ∝ |y|^p·sign y, p estimated: a tank draining through an orifice",
            (),
            "estimated",
            functools.partial(
                power_law_terms, "y", lags_y, STIFFNESS_EXPONENTS, STIFFNESS_LAWS, integer_above=True
            ),
            integer_laws=STIFFNESS_LAWS,
            searched=1,
            kinked_law=True,
        ),
        Effect(
            "power_law_damping",
            "damping ∝ |dy|^p·sign dy, p estimated: flow through an orifice, turbulent drag",
            (),
            "estimated",
            functools.partial(power_law_terms, "dy", lags_y, DAMPING_EXPONENTS, DAMPING_LAWS),
        ),
        Effect(
            "input_dead_zone",
            "a dead zone in the actuator: no force until the command exceeds a width, estimated",
            (),
            "estimated",
            functools.partial(input_play_terms, "deadzone", x_lags),
        ),
        Effect(
            "input_backlash",
            "backlash (play) in the actuator's drive, of a width estimated",
            (),
            "estimated",
            functools.partial(input_play_terms, "backlash", x_lags),
        ),
    ]


def _structure_effects(terms: Sequence[Term], ny: int, x_lags: Sequence[int]) -> list[Effect]:
    """The effects on the output side and in the model's form: saturation, lags, an offset, the
    generic polynomial, a periodic disturbance and coloured noise."""
    shorter_delay = [x_lags[0] - 1] if x_lags[0] > 0 else []
    return [
        Effect(
            "output_saturation",
            "the output saturates: plateaus at the record's range ends (overflow, end stops, a "
            "clipping sensor)",
            (),
            "saturation",
        ),
        Effect(
            "rectified_output",
            "the sensor reads a magnitude, blind to the sign (a pulse counter on a shaft turning "
            "either way): the dynamics run on a signed output z and the reading is |z|",
            (),
            "rectified",
        ),
        Effect(
            "missing_lags",
            "dynamics beyond the declared lags, or a shorter input delay",
            _powers("y", [ny + 1, ny + 2], 1) + _powers("x", [x_lags[-1] + 1, *shorter_delay], 1),
        ),
        offset_effect(terms),
        polynomial_effect(terms),
        Effect(
            "periodic_disturbance",
            "a periodic force or interference at a residual spectral peak",
            (),
            "periodic",
        ),
        MOVING_AVERAGE_NOISE,
    ]


def polynomial_effect(terms: Sequence[Term]) -> Effect:
    """The generic polynomial NARX's terms of degree 2: every product of two of the model's own
    shortest lags of y and x (``POLYNOMIAL_LAGS`` of each), y[t-i]·x[t-j], y[t-i]·y[t-j],
    x[t-i]·x[t-j]. They name no physical effect; they are what an identifier tries where no named
    family explains the data, and the loop offers them after every named family
    (:func:`models.refinement.refine`). Products of every lag would grow as the square of the
    order (231 for ARX(10, 10) with x[t]) and make each round's scoring that much slower."""
    lags = _shortest_lags(terms)
    factors = [Factor(signal, lag) for signal, chosen in lags.items() for lag in chosen]
    return Effect(
        POLYNOMIAL,
        "products of two of the model's lags, no physical effect named: the generic polynomial NARX "
        "of degree 2",
        tuple(Term.of(pair) for pair in itertools.combinations_with_replacement(factors, 2)),
    )


def bilinear_effect(terms: Sequence[Term]) -> Effect:
    """Dynamics the input modulates: the products y[t-i]·x[t-j] of the model's shortest lags of y
    and x (``POLYNOMIAL_LAGS`` of each, as the generic polynomial's), a bilinear system's terms.

    In a bilinear system the input scales the output's own terms, y[t] = Σ (a_i + b_ij·x[t-j])·y[t-i]
    + …: its poles move with the input. A drive that switches a motor/generator's circuit (the
    machine coasting when it is off) changes its damping so, and a binary drive hides it from the
    input's own powers (x² = 5x for x ∈ {0, 5}). The other named families hold products of y with y
    or of x with x only, and the generic polynomial, which holds these too, names nothing and is
    judged after them: without this family the loop named stand-ins first (a power law of y, a
    cubic spring), each fitting a slice of the modulation."""
    lags = _shortest_lags(terms)
    return Effect(
        "bilinear",
        "dynamics the input modulates (a bilinear system): products y[t-i]·x[t-j], the input scaling "
        "the output's own terms, as a switched drive changes a motor's damping",
        tuple(Term.of((Factor("y", i), Factor("x", j))) for i in lags["y"] for j in lags["x"]),
    )


def _shortest_lags(terms: Sequence[Term]) -> dict[str, list[int]]:
    """The model's ``POLYNOMIAL_LAGS`` shortest lags of y and of x."""
    return {
        signal: sorted({f.lag for t in terms for f in t.factors if f.signal == signal})[:POLYNOMIAL_LAGS]
        for signal in ("y", "x")
    }


def unused(effects: Sequence[Effect], terms: Sequence[Term]) -> list[Effect]:
    """The effects with the terms the model already has left out; those with none left dropped
    (those whose regressors come from the data or the residual always stay)."""
    present = set(terms)
    kept = []
    for effect in effects:
        new = tuple(t for t in effect.terms if t not in present)
        if new or effect.kind in ("periodic", "noise", "estimated", "saturation", "rectified"):
            kept.append(replace(effect, terms=new))
    return kept


def offset_effect(terms: Sequence[Term]) -> Effect:
    """An offset c of the measured output (a sensor's bias, or a static load): y reads the state
    plus c, and the model's terms should read y − c.

    Where the model's terms hold a power or a product of y, c shows through them: one regressor,
    ∂ŷ/∂c at c = 0 (:func:`offset_direction`), adding the constant and the terms an offset brings
    into them ("output_shift"); so too where the model holds a constant already, whose offset's
    squares follow a power of y once one enters. A linear model without a constant is offered
    the constant first, and where the constant explains the residual the offset is that constant.
    Where it does not, the model's poles reach the shift and the offset shows only through a
    nonlinearity that reads the state, not y: on the 2-DOF rig with an offset c, its cubic spring
    acts on (y − c)³ = y³ − 3c·y² + 3c²·y − c³, and a cube of y alone stood for it so badly that it
    never entered, nor the offset's squares after it. So there the offset is offered with the
    cube it shows through: the cube of y − c at each of the model's lags of y, c estimated beside
    the cubes' coefficients (:func:`offset_cube`), one regressor spanned by the constant, the
    squares and the cubes ("combined", its constant tested first: ``Effect.evidence_first``).
    Without an offset c comes out near zero, and the cubic spring's family, with half the terms,
    ranks before it. Where the constant shows (Silverbox from ``linear:4,4``, which the rounds
    give the constant after cubic damping), taking the cube in its place, or after it, put the
    cubes and squares in one round where the cubic and quadratic springs had come in turn, and
    the model ran free over the arrow 13 % and 44 % further off."""
    shifted = offset_terms(terms)
    lags = sorted({t.factors[0].lag for t in terms if _plain_y(t)})
    if len(shifted) > 1 or not lags or Term() in terms:
        return Effect(OFFSET, OFFSET_DESCRIPTION, shifted, "output_shift")
    monomials = (Term(), *(Term((Factor("y", k, power),)) for power in (2, 3) for k in lags))
    return Effect(
        OFFSET,
        OFFSET_DESCRIPTION + ", seen through a cubic restoring force: (y − c)³, c estimated",
        monomials,
        "combined",
        combine=functools.partial(offset_cube, tuple(lags), monomials),
        searched=len(lags),
        evidence_first=True,
    )


def offset_cube(
    lags: Sequence[int],
    monomials: Sequence[Term],
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    residual: np.ndarray,
    terms: Sequence[Term],
    lag: int,
) -> tuple[tuple[Term, ...], np.ndarray]:
    """Σ_k w_k·(y[t-k] − c)³ over the ``lags``, for the offset c and weights w that, beside the
    model's regressors (the plain lags of y among them), best explain the residual; the
    ``monomials`` that span it beside the model's (the constant, the squares and the cubes), and
    the regressor itself over the stacked rows lag … N−1 of every record (``residual`` runs over
    the same rows).

    Separable least squares: for a c, w is the least-squares fit of the shifted cubes, made
    orthogonal to the model's regressors, to the residual; c is searched on a grid of
    ``PROFILE_POINTS`` over the output's range, then by a bounded scalar search between the best
    point's neighbours. The search reads the first ``SEARCH_ROWS`` rows of the first record; c
    and w are then fixed, and the regressor is built on every record. A record too short for
    the span (ten equations per monomial) is not offered the family."""
    x0, y0 = records[0]
    rows = len(y0) - lag
    stacked = sum(len(y) - lag for _, y in records)
    if not np.any(residual[:rows]) or 10 * len(monomials) > min(rows, SEARCH_ROWS):
        return (), np.zeros(stacked)
    x, y, part, model_basis = _search_part(x0, y0, residual[:rows], terms, lag)
    plain = [Term((Factor("y", k),)) for k in lags]
    lagged, _ = regressor_matrix(plain, x, y, lag)

    def fitted(c: float) -> tuple[float, np.ndarray]:
        columns = _off_model(model_basis, (lagged - c) ** 3)
        weights, *_ = linalg.lstsq(columns, part, lapack_driver="gelsd")
        remaining = part - columns @ weights
        return float(remaining @ remaining), weights

    c = _profile_least(lambda c: fitted(c)[0], float(np.min(y)), float(np.max(y)))
    assert c is not None  # open below and above
    weights = fitted(c)[1]
    everywhere = np.concatenate(
        [(regressor_matrix(plain, xr, yr, lag)[0] - c) ** 3 @ weights for xr, yr in records]
    )
    return _spanning(monomials, x, y, lag, model_basis), everywhere


def offset_terms(terms: Sequence[Term]) -> tuple[Term, ...]:
    """The constant and every monomial an offset c of y adds to the model to first order in c:
    each y factor of power p contributes the term with that factor's power lowered by one."""
    lowered = [Term()]
    for term in terms:
        for index in _y_factors(term):
            lowered.append(_lower(term, index))
    return tuple(dict.fromkeys(lowered))


def offset_direction(
    terms: Sequence[Term], theta: np.ndarray, x: np.ndarray, y: np.ndarray, lag: int
) -> np.ndarray:
    """∂ŷ/∂c for a model ŷ[t] = c + F(y − c, x) at c = 0, rows t = lag … N−1:

        g[t] = 1 − Σ_j θ_j Σ_{y factors f of term j} p_f · φ_j^(f↓)[t],

    where φ_j^(f↓) is term j with the power p_f of factor f lowered by one. A sensor offset c
    adds c·g to the one-step prediction, so g is the one regressor that tests for it.
    """
    lowered: list[Term] = []
    weights: list[float] = []
    for term, coefficient in zip(terms, theta, strict=True):
        for index in _y_factors(term):
            lowered.append(_lower(term, index))
            weights.append(coefficient * term.factors[index].power)
    direction = np.ones(len(y) - lag)
    if lowered:
        columns, _ = regressor_matrix(lowered, x, y, lag)
        direction -= columns @ np.asarray(weights)
    return direction


def _plain_y(term: Term) -> bool:
    """Whether ``term`` is a plain lag of y, y[t-k]."""
    if len(term.factors) != 1:
        return False
    factor = term.factors[0]
    return factor.signal == "y" and factor.power == 1 and not factor.function


def _y_factors(term: Term) -> list[int]:
    return [i for i, factor in enumerate(term.factors) if factor.signal == "y"]


def _lower(term: Term, index: int) -> Term:
    factor = term.factors[index]
    rest = [f for i, f in enumerate(term.factors) if i != index]
    if factor.power > 1:
        rest.append(Factor(factor.signal, factor.lag, factor.power - 1))
    return Term.of(rest)


def periodic_terms(residual: np.ndarray, alpha: float, x: np.ndarray) -> tuple[Term, ...]:
    """A sine and a cosine at each significant peak of the residual's spectrum that the input
    ``x`` does not excite.

    Peaks come from :func:`models.spectrum.residual_spectrum` at level ``alpha``; Welch's bins
    are far too coarse for a regressor that must stay in phase over the whole record, so each
    frequency is then refined to the maximum of the periodogram |Σ e[t]·exp(−2πi·f·t)|² near
    the peak: on an 8× zero-padded FFT grid, then by a bounded scalar search within one grid step.
    A peak whose frequency lies on one of the input's lines, or on their harmonics and
    intermodulation products (:func:`models.spectrum.excited_intervals`), is the periodic
    residual a wrong model leaves under a periodic input, not an external tone: it is left out.
    """
    spectrum = residual_spectrum(residual, 1.0, alpha)
    if not spectrum.peaks:
        return ()
    excited = _excited(np.asarray(x, dtype=np.float64).tobytes(), alpha)
    n = residual.size
    # At least 8n, of a length whose FFT is fast: 8n itself can hold a large prime factor (a
    # fifth of a second on Silverbox's 65 000 samples where a fast length takes a fiftieth).
    padded = scipy.fft.next_fast_len(8 * n, real=True)
    power = np.abs(scipy.fft.rfft(residual - residual.mean(), padded)) ** 2
    grid = scipy.fft.rfftfreq(padded)
    times = np.arange(n, dtype=np.float64)
    half_bin = 0.5 / (spectrum.frequencies.size - 1)  # half a Welch bin, in cycles per sample

    def periodogram(f: float) -> float:
        return -(abs(np.dot(residual, np.exp(-2j * np.pi * f * times))) ** 2)

    terms: list[Term] = []
    for peak in spectrum.peaks:
        near = np.flatnonzero(np.abs(grid - peak.frequency) <= half_bin)
        coarse = grid[near[np.argmax(power[near])]]
        step = 1.0 / padded
        low, high = max(coarse - step, 1e-9), min(coarse + step, 0.5 - 1e-9)
        frequency = float(scipy.optimize.minimize_scalar(periodogram, bounds=(low, high), method="bounded").x)
        if np.any((excited[:, 0] <= frequency) & (frequency <= excited[:, 1])):
            continue
        # Rounded so that the term's name stays short; the phase error this leaves over 10⁶
        # samples is below 10⁻³ of a cycle.
        frequency = float(f"{frequency:.10g}")
        terms += [Term((Factor(wave, 0, frequency=frequency),)) for wave in WAVES]
    return tuple(dict.fromkeys(terms))


@functools.lru_cache(maxsize=1)
def _excited(x: bytes, alpha: float) -> np.ndarray:
    """:func:`models.spectrum.excited_intervals` of the input (as bytes), read-only. Kept for the
    next call: the input is the same round after round (70 ms on Silverbox's 65 000 samples)."""
    intervals = excited_intervals(np.frombuffer(x), 1.0, alpha)
    intervals.flags.writeable = False
    return intervals


def output_limits(y: np.ndarray) -> tuple[float, float] | None:
    """The levels the output saturates at: its maximum (minimum) if at least
    ``PLATEAU_SAMPLES`` consecutive samples sit exactly there, ±inf for a side without a
    plateau; None if neither side has one."""

    def plateau(level: float) -> bool:
        at = np.concatenate(([False], y == level, [False])).astype(np.int8)
        edges = np.flatnonzero(np.diff(at))
        return bool(edges.size) and int(np.max(edges[1::2] - edges[::2])) >= PLATEAU_SAMPLES

    low, high = float(np.min(y)), float(np.max(y))
    limits = (low if plateau(low) else -np.inf, high if plateau(high) else np.inf)
    return None if limits == (-np.inf, np.inf) or low == high else limits


def records_output_limits(records: Iterable[tuple[Any, np.ndarray]]) -> tuple[float, float] | None:
    """:func:`output_limits` of the outputs of all the ``(x, y)`` ``records`` together: one
    sensor reads them all."""
    return output_limits(np.concatenate([np.asarray(y, dtype=np.float64) for _, y in records]))


def reads_magnitude(y: np.ndarray) -> bool:
    """Whether the output ``y`` reads as a magnitude: it never goes below zero and comes down to
    it, both within ``MAGNITUDE_SLACK`` of its range. A signed quantity seen through a sensor
    blind to its sign does; a level far from zero (a tank half full) never shows where the sign
    would turn, and a signed output crosses zero."""
    low, high = float(np.min(y)), float(np.max(y))
    return high > 0 and abs(low) <= MAGNITUDE_SLACK * (high - low)


def magnitude_direction(prediction: np.ndarray) -> np.ndarray:
    """|ŷ| − ŷ: what reading the magnitude of the one-step prediction ŷ changes. A model whose
    sensor reads a magnitude has this regressor with coefficient one, where its prediction on the
    readings goes below zero."""
    return np.abs(prediction) - prediction


def saturation_direction(prediction: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """clip(ŷ) − ŷ: what clipping the one-step prediction ŷ to the output limits changes. A model
    whose output saturates there has this regressor with coefficient one."""
    return np.clip(prediction, *limits) - prediction


def profile_search(
    build: Callable[[float], tuple[Term, ...]],
    bounds: tuple[float, float],
    search: SearchInput,
    log_scale: bool = False,
    open_above: bool = False,
) -> tuple[Term, ...]:
    """The terms ``build(p)`` for the parameter p in ``bounds`` whose regressors, beside the
    model's, explain most of the residual (rows lag … N−1): a grid of ``PROFILE_POINTS``, then a
    bounded scalar search between the best point's neighbours; p rounded to 4 digits so that
    the terms' names stay short. The search reads the first ``SEARCH_ROWS`` rows. With
    ``open_above``, a best point at the grid's high end is no estimate (what lies beyond is
    another family's): none."""
    x, y, unexplained = _unexplained(search)

    def at(p: float) -> float:
        columns, _ = regressor_matrix(list(build(float(np.exp(p) if log_scale else p))), x, y, search.lag)
        return unexplained(columns)

    low, high = (np.log(bounds[0]), np.log(bounds[1])) if log_scale else bounds
    p = _profile_least(at, low, high, open_above)
    if p is None:
        return ()
    return build(float(f"{np.exp(p) if log_scale else p:.4g}"))


def _profile_least(
    at: Callable[[float], float], low: float, high: float, open_above: bool = False
) -> float | None:
    """The p in [``low``, ``high``] where ``at`` is least: a grid of ``PROFILE_POINTS``, then a
    bounded scalar search between the best point's neighbours (the grid's best where the search
    finds nothing lower). With ``open_above``, None where the grid's best is its high end."""
    grid = np.linspace(low, high, PROFILE_POINTS)
    values = [at(float(p)) for p in grid]
    best = int(np.argmin(values))
    if open_above and best == len(grid) - 1:
        return None
    refined = scipy.optimize.minimize_scalar(
        lambda p: at(float(p)),
        bounds=(grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]),
        method="bounded",
        options={"xatol": 1e-3 * (high - low)},
    )
    return float(refined.x) if refined.fun <= values[best] else float(grid[best])


def _unexplained(search: SearchInput) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], float]]:
    """The part of the record a search for a family's parameters reads (x and y up to the first
    ``SEARCH_ROWS`` rows) and what it minimises: the residual's sum of squares that the family's
    regressors over those rows (lag … on), beside the model's, leave unexplained (the whole
    residual where a regressor is not finite or vanishes)."""
    x, y, residual, model_basis = _search_part(search.x, search.y, search.residual, search.terms, search.lag)

    def unexplained(columns: np.ndarray) -> float:
        norms = column_norms(columns)
        if not np.all(np.isfinite(norms)) or not np.all(norms > 0):
            return float(residual @ residual)
        columns = orthogonal_part(columns / norms, model_basis)
        fit, *_ = linalg.lstsq(columns, residual, lapack_driver="gelsd")
        remaining = residual - columns @ fit
        return float(remaining @ remaining)

    return x, y, unexplained


def power_law_terms(
    signal: str,
    lags: Sequence[int],
    exponents: tuple[float, float],
    integers: Sequence[tuple[str, float]],
    search: SearchInput,
    integer_above: bool = False,
) -> tuple[Term, ...]:
    """|s[t-k]|^p·sign s[t-k] at each lag, s = y or dy, p in ``exponents`` estimated; none if
    the model has such a law already (one exponent per law), nor where an integer law of the
    signal that a family names (``integers``) explains the residual better than the exponent found,
    beyond that exponent's uncertainty (:func:`integer_law_better`): the effect is that law, its own
    family's. With
    ``integer_above``, where an integer law a family names lies just above the range (y's cubic
    above the stiffness law's), none either where the best exponent is the range's end below it:
    the residual asks for a law beyond the range, that family's, which the law at the end only
    imitates (on the rig with a quadratic spring, nothing declared, a law at the end, p = 2.6,
    came in after the rig's cubic and quadratic springs, the model complete, and the model ran
    free over another record more than twice as far off)."""
    if _has(search.terms, signal, "spow"):
        return ()

    def build(p: float) -> tuple[Term, ...]:
        return tuple(Term((Factor(signal, k, function="spow", parameter=p),)) for k in lags)

    found = profile_search(build, exponents, search, open_above=integer_above)
    if not found or integer_law_better(signal, lags, found[0].factors[0].parameter, integers, search):
        return ()
    return found


def integer_law_better(
    signal: str,
    lags: Sequence[int],
    exponent: float | None,
    integers: Sequence[tuple[str, float]],
    search: SearchInput,
) -> str | None:
    """The family of the integer law (of ``integers``, by exponent; the one nearest the ``exponent``
    fitted first) that explains the residual better than the law |s[t-k]|^p·sign s[t-k] of the
    ``signal`` at the ``lags``, p the ``exponent`` (:func:`power_law_terms`), beyond the exponent's
    uncertainty: the law with its exponent fixed at the integer leaves the residual's sum of
    squares S_k where the fitted one leaves S, and n·ln(S/S_k) over the n rows the search read
    exceeds the χ² quantile of one degree of freedom at ``EXPONENT_ALPHA`` (the likelihood-ratio
    test of the exponent, Wilks); None where none does.

    The range searched stops short of the integer laws, each its own family's; inside it the
    fitted exponent is the profile's least, and no integer law beyond explains more. Where the
    best exponent is an end of the range and the integer law beyond it explains more by more
    than the exponent's uncertainty, the data reject every exponent of the range for that law:
    the law at the end is the integer law seen through the search, a stand-in its own family,
    scored beside it, names better (on the 2-DOF rig with Coulomb friction or quadratic damping
    planted the damping law came in first at its range's end, 0.2 or 1.8, and the integer law
    beside it a round or two later). Where the data cannot tell the two apart (Silverbox's
    damping law at 1.8 and the quadratic law), the fitted law keeps its place."""
    if exponent is None or not integers:
        return None
    x, y, unexplained = _unexplained(search)
    rows = len(y) - search.lag
    # The signal itself at each lag, raised here: an exponent of zero (the sign, Coulomb's law) is
    # no term's parameter.
    base, _ = regressor_matrix([Term((Factor(signal, k),)) for k in lags], x, y, search.lag)

    def left(p: float) -> float:
        return unexplained(np.sign(base) * np.abs(base) ** p)

    fitted = left(exponent)
    bound = float(scipy.stats.chi2.ppf(1 - EXPONENT_ALPHA, 1))
    for name, integer in sorted(integers, key=lambda law: abs(law[1] - exponent)):
        below = left(integer)
        if below > 0 and rows * np.log(fitted / below) > bound:
            return name
    return None


def input_play_terms(function: str, lags: Sequence[int], search: SearchInput) -> tuple[Term, ...]:
    """deadzone(x[t-k], w) or backlash(x[t-k], w) at the model's input lags, the half-width w
    estimated between 1 % and 150 % of the input's standard deviation (on a log scale); none if
    the model has one already."""
    scale = float(np.std(search.x))
    if not scale > 0 or _has(search.terms, "x", function):
        return ()

    def build(w: float) -> tuple[Term, ...]:
        return tuple(Term((Factor("x", k, function=function, parameter=w),)) for k in lags)

    return profile_search(build, (0.01 * scale, 1.5 * scale), search, log_scale=True)


def unmeasured_cube(cubics: Sequence[Term]) -> Combiner:
    """The combiner of u[t]³ for the combination u[t] = Σ_k c_k·y[t-k] of y's lags whose cube, beside
    the model's regressors, best explains the residual, spanned by ``cubics`` (:func:`combination_terms`).

    A spring k·u³ on a coordinate the sensor does not see, u, enters the response through the
    linear dynamics, and u itself is a linear combination of the response's lags (on the 2-DOF
    rig, x1 = (m2·ẍ2 + c2·ẋ2 + k2·x2 + k3·x2³)/k2 from mass 2's equation). The cube's expansion
    is a sum of cubics of y[t-m] and dy[t-1] … dy[t-m+1] (the same span as the cross-lag cubics of
    y's lags, far better conditioned).
    """
    lags = range(1, max(f.lag for t in cubics for f in t.factors if f.signal == "y") + 1)
    return functools.partial(combination_terms, "y", lags, UNMEASURED_POWERS, cubics)


def filtered_input_powers(lags: Sequence[int], monomials: Sequence[Term]) -> Combiner:
    """The combiner of a·u[t]² + b·u[t]³ for the combination u[t] = Σ_k c_k·x[t-k] of the input's
    ``lags`` that, beside the model's regressors, best explains the residual, spanned by the
    ``monomials`` of degree 2 and 3 of those lags (:func:`combination_terms`).

    A Wiener–Hammerstein system y = G2(f(G1 x)) passes the input through a filter G1, a static
    nonlinearity f(v) = v + a·v² + b·v³ + …, then a filter G2. A linear model holds G2·G1; what
    it lacks is G2 applied to a·v² + b·v³, with v = G1 x a combination of x's lags (exactly so for
    a finite impulse response, nearly so within the model's lags otherwise), G2's poles already
    among the model's y lags (its numerator's lags shift the combination: only as far as the
    model's input lags reach are they held). An asymmetric f (a diode) has both an even and an odd part, and
    both are powers of the same v: searching c on the cube alone would ignore the even part's
    evidence (and a diode near its knee is mostly even), on the square alone the odd part's. So c
    is sought on a·u² + b·u³ jointly, a and b eliminated by separable least squares; no constant
    beside them, since the square carries the mean it adds to the output. The monomials, then
    estimated freely, hold the square and cube of every combination of the lags: products across
    lags, where the input nonlinearity's powers of each lag alone hold a static nonlinearity
    before the dynamics (Hammerstein).
    """
    return functools.partial(combination_terms, "x", lags, FILTERED_POWERS, monomials)


def combination_parameters(lags: Sequence[int], degrees: Sequence[int]) -> int:
    """The parameters :func:`combination_terms` fits to the residual beyond its regressor's one
    coefficient: the combination's direction over the ``lags`` (its length is immaterial, the
    powers' coefficients absorb it) and the ratios of the ``degrees``' coefficients. Its one
    regressor is the best of a family of that many dimensions, and is tested so."""
    return max(len(lags) - 1, 0) + len(degrees) - 1


def combination_terms(
    signal: Literal["y", "x"],
    lags: Sequence[int],
    degrees: Sequence[int],
    monomials: Sequence[Term],
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    residual: np.ndarray,
    terms: Sequence[Term],
    lag: int,
) -> tuple[tuple[Term, ...], np.ndarray]:
    """g(u[t]) = Σ_d a_d·u[t]^d over ``degrees`` for the combination u[t] = Σ_k c_k·s[t-k] of the
    signal's ``lags`` (s = y or x) whose powers, beside the model's regressors, best explain the
    residual; the ``monomials`` that span g(u) beside the model's, and g(u) itself over the stacked
    rows lag … N−1 of every record (``residual`` runs over the same rows).

    The search is separable least squares (variable projection; Golub & Pereyra, *Inverse
    Problems* 19, 2003): for a direction c the coefficients a_d are those of the least-squares fit
    of the powers u^d, each made orthogonal to the model's regressors, to the residual, so that c
    alone is sought, by nonlinear least squares (Kaufman's Jacobian) from equal weights of the
    first ``COMBINATION_STARTS`` sign patterns; c's length is immaterial (the a_d absorb it). On y
    the combination is a nearly cancelling one (an acceleration is a second difference), so c is
    sought in the backward differences of y at the oldest lag; on x in the lags themselves; either
    way each basis column is scaled to unit spread on the first record. g(u) expands into
    monomials of the lags of the degrees given, which the model then estimates freely:
    ``monomials``, less those the model's own terms already span (a pivoted QR decides). The
    search reads the first ``SEARCH_ROWS`` rows of the first record; the combination it finds is
    a fixed function of the lags, so the regressor is built on every record with it. A
    combination of fewer than two lags, or a record too short for the span (ten equations per
    monomial, and more rows than columns for the pivoted QR), is not offered the family.
    """
    x0, y0 = records[0]
    rows = len(y0) - lag
    stacked = sum(len(y) - lag for _, y in records)
    too_short = 10 * len(monomials) > min(rows, SEARCH_ROWS)
    if len(lags) < 2 or not monomials or not np.any(residual[:rows]) or too_short:
        return (), np.zeros(stacked)
    first = _combination_basis(signal, lags, x0, y0, lag)
    spread = np.std(first, axis=0)
    if not np.all(spread > 0):
        return (), np.zeros(stacked)
    x, y, residual, model_basis = _search_part(x0, y0, residual[:rows], terms, lag)
    basis = first[: len(residual)] / spread
    spanning = _spanning(monomials, x, y, lag, model_basis)
    powers = np.asarray(degrees)
    c, a = _combination(basis, model_basis, residual / np.std(residual), powers, len(lags))
    everywhere = np.concatenate(
        [(_combination_basis(signal, lags, xr, yr, lag) / spread) @ c for xr, yr in records]
    )
    return spanning, integer_powers(everywhere, powers) @ a


def _off_model(model_basis: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """``columns`` made orthogonal to the model's regressors (``model_basis``, orthonormal)."""
    return columns - model_basis @ (model_basis.T @ columns)


def _spanning(
    monomials: Sequence[Term], x: np.ndarray, y: np.ndarray, lag: int, model_basis: np.ndarray
) -> tuple[Term, ...]:
    """The ``monomials`` that span g(u) beside the model's regressors: those whose columns, off
    the model, a pivoted QR finds independent, in their order; none where the model's own terms
    span them all."""
    columns, _ = regressor_matrix(list(monomials), x, y, lag)
    columns = _off_model(model_basis, columns / column_norms(columns))
    # The pivots of a pivoted QR depend on the columns' inner products alone: those of R.
    _, triangle, pivots = linalg.qr(linalg.qr(columns, mode="r")[0], mode="economic", pivoting=True)
    # Each column had unit norm before the model was taken off it: what is left is judged against
    # that, not against the largest remainder. Where the model already spans every monomial (its
    # own terms among them), the remainders are all rounding, and judged against the largest
    # they would all pass and the family would put the model's own terms into it again.
    independent = pivots[np.abs(np.diag(triangle)) > 1e-8]
    return tuple(monomials[i] for i in sorted(independent))


def _combination(
    basis: np.ndarray, model_basis: np.ndarray, target: np.ndarray, powers: np.ndarray, n_lags: int
) -> tuple[np.ndarray, np.ndarray]:
    """The direction c in ``basis`` whose powers u^d (u = basis·c), off the model, best fit the
    ``target``, by separable least squares from the first ``COMBINATION_STARTS`` sign patterns;
    c (one weight for each of the ``n_lags`` basis columns) and the powers' coefficients a_d."""

    # Kept for the last c: the search asks for the Jacobian where it has just evaluated.
    @functools.lru_cache(maxsize=1)
    def projected_at(c: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        u = basis @ np.frombuffer(c)
        q, r = linalg.qr(_off_model(model_basis, integer_powers(u, powers)), mode="economic")
        return u, q, linalg.lstsq(r, q.T @ target)[0]

    def projected(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """u, the orthonormal basis of the powers u^d off the model, and their coefficients a_d."""
        return projected_at(np.asarray(c, dtype=np.float64).tobytes())

    def misfit(c: np.ndarray) -> np.ndarray:
        _, q, _ = projected(c)
        return target - q @ (q.T @ target)

    def jacobian(c: np.ndarray) -> np.ndarray:
        # Kaufman's approximation: ∂/∂c of the fitted g(u) off the model, then off the powers.
        u, q, a = projected(c)
        slope = integer_powers(u, powers - 1) @ (powers * a)  # g'(u)
        change = _off_model(model_basis, slope[:, None] * basis)
        return -(change - q @ (q.T @ change))

    best = None
    for signs in itertools.islice(itertools.product((1.0, -1.0), repeat=n_lags - 1), COMBINATION_STARTS):
        start = np.array((1.0, *signs)) / np.sqrt(n_lags)
        fit = scipy.optimize.least_squares(misfit, start, jac=jacobian, max_nfev=100)
        if best is None or fit.cost < best.cost:
            best = fit
    *_, a = projected(best.x)
    return best.x, a


def integer_powers(u: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """The columns u^d for each of the non-negative integer ``degrees``, by repeated
    multiplication: numpy's pow takes about 60 ns an element, which made three quarters of the
    combination searches' time."""
    table = [np.ones_like(u)]
    for _ in range(int(np.max(degrees, initial=0))):
        table.append(table[-1] * u)
    return np.column_stack([table[d] for d in degrees])


def _combination_basis(
    signal: Literal["y", "x"], lags: Sequence[int], x: np.ndarray, y: np.ndarray, lag: int
) -> np.ndarray:
    """The columns a combination of the signal's lags is sought in, over rows lag … N−1: for y the
    backward differences at the oldest lag (y[t-m], then the first, second, … differences of
    y[t-m] … y[t-1]), for x the lags themselves."""
    if signal == "x":
        return np.column_stack([x[lag - k : len(x) - k] for k in lags])
    ordered = sorted(lags, reverse=True)  # y[t-m] … y[t-1]
    lagged = np.column_stack([y[lag - k : len(y) - k] for k in ordered])
    return np.column_stack([np.diff(lagged, n, axis=1)[:, 0] for n in range(len(ordered))])


def hysteresis_terms(lags: Sequence[int], search: SearchInput) -> tuple[Term, ...]:
    """boucwen(y[t-k], w, r) at each lag, the level w between 1 % and ten times y's standard
    deviation (on a log scale) and the shape r = γ/β within ``BOUC_WEN_SHAPES`` estimated
    together; none if the model has one already. At the ends of those ranges z is no loop: a
    sign of the velocity (Coulomb friction) at the lowest level, y itself with a correction of
    y·|y| (a spring) at the highest, a stiffening spring at the lowest shape. A force k·z on a
    coordinate y reaches y through the dynamics, at the model's lags.

    The two are sought on a grid of ``PROFILE_POINTS`` levels by the shapes' grid, then by a
    simplex search within the best point's neighbours; each rounded to 4 digits. A best point at
    an end of either grid is no estimate: the family is not offered. The search runs
    z once for each point and reads its lags from that run: the terms' regressors each start z
    at their first row, which the search's columns differ from only while z forgets its start."""
    scale = float(np.std(search.y))
    if not scale > 0 or _has(search.terms, "y", "boucwen"):
        return ()

    def build(w: float, r: float) -> tuple[Term, ...]:
        return tuple(Term((Factor("y", k, function="boucwen", parameter=w, shape=r),)) for k in lags)

    _, y, unexplained = _unexplained(search)

    def at(p: np.ndarray) -> float:
        z = bouc_wen(y, float(np.exp(p[0])), float(p[1]))
        return unexplained(np.column_stack([z[search.lag - k : len(z) - k] for k in lags]))

    levels = np.linspace(np.log(0.01 * scale), np.log(10.0 * scale), PROFILE_POINTS)
    shapes = np.linspace(*BOUC_WEN_SHAPES)
    values = np.array([[at(np.array((w, r))) for r in shapes] for w in levels])
    i, j = np.unravel_index(int(np.argmin(values)), values.shape)
    if i in (0, len(levels) - 1) or j in (0, len(shapes) - 1):
        # The residual asks for z beyond the family's ranges: not a hysteresis it holds, but a
        # force its terms imitate there (Silverbox's cubic spring, by the lowest shape).
        return ()
    box = [(grid[k - 1], grid[k + 1]) for grid, k in ((levels, i), (shapes, j))]  # i, j are inside
    start = np.array((levels[i], shapes[j]))
    refined = scipy.optimize.minimize(
        at,
        start,
        method="Nelder-Mead",
        bounds=box,
        options={"xatol": 1e-3, "fatol": 1e-9 * values[i, j], "maxfev": 60},
    )
    w, r = refined.x if refined.fun <= values[i, j] else start
    return build(float(f"{np.exp(w):.4g}"), float(f"{r:.4g}"))


def _search_part(
    x: np.ndarray, y: np.ndarray, residual: np.ndarray, terms: Sequence[Term], lag: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first ``SEARCH_ROWS`` rows of the record (x and y up to them) and of the residual, the
    latter made orthogonal to the model's regressors over those rows, with their orthonormal basis."""
    end = lag + min(len(residual), SEARCH_ROWS)
    x, y = (np.asarray(signal[:end], dtype=np.float64) for signal in (x, y))
    model_basis = _model_basis(tuple(terms), lag, x.tobytes(), y.tobytes())
    residual = residual[: end - lag]
    return x, y, residual - model_basis @ (model_basis.T @ residual), model_basis


@functools.lru_cache(maxsize=1)
def _model_basis(terms: tuple[Term, ...], lag: int, x: bytes, y: bytes) -> np.ndarray:
    """An orthonormal basis of the model's regressors over the rows a search reads (x and y up to
    them, as bytes), read-only. Kept for the next call: a round's searched families read the same
    rows with the same model, and each took 20 ms to make it (Silverbox's 51 terms)."""
    Phi, _ = regressor_matrix(list(terms), np.frombuffer(x), np.frombuffer(y), lag)
    basis, _ = linalg.qr(divided_columns(Phi, column_norms(Phi)), mode="economic", overwrite_a=True)
    basis.flags.writeable = False
    return basis


def _has(terms: Sequence[Term], signal: str, function: str) -> bool:
    return any(f.signal == signal and f.function == function for t in terms for f in t.factors)
