"""What the data can support in the loop's first round on a planted record, nothing declared: from
the loop's own start on the record's head (its linear orders chosen as :func:`models.refinement.refine`
chooses them, the held-out tail left out), the fall of the check blocks' free run — the one-step
criterion's figure — that each candidate brings: the families the round scores significant, in
the one-step order, the rig's own cubic spring at every lag, and the planted family with its
parameters set or searched on that figure itself (a periodic force's sine and cosine at the
simulated frequency; a Bouc–Wen variable's level and shape on the family's grid, its ends left
out as the family leaves them; an offset with the rig's spring and the squares it brings; a
quadratic spring, Coulomb friction or quadratic damping at every lag; a power-law spring's or
power-law damping's exponent or a dead zone's or backlash's width at the simulated value and
searched on the family's grid, alone and beside the rig's spring, on which the planted effect
sits). Where the planted family searched so falls less than another family, naming it first is
not what the data supports on that record.

Run from the project root on development seeds (below 1000)::

    .venv/bin/python -m bench.first_round --first-seed 1 --seeds 4 \\
        --only periodic_disturbance hysteresis offset
    .venv/bin/python -m bench.first_round --first-seed 1 --seeds 4 --samples 4000 \\
        --only input_dead_zone quadratic_stiffness power_law_stiffness coulomb_friction
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.planted import CASES, TEST, Case
from models.checking import CheckSplit, Structure
from models.effects import (
    BOUC_WEN_SHAPES,
    DAMPING_EXPONENTS,
    PROFILE_POINTS,
    STIFFNESS_EXPONENTS,
    candidate_effects,
    unused,
)
from models.held_out import held_out_tails
from models.linear_start import choose_linear
from models.round_criteria import DEFAULT_ALPHA, scored
from models.scoring import EffectScore
from models.terms import parse_terms
from simulator.simulate import simulate

SAMPLES = 1600
SCORED = 4  # the significant families shown, first in the one-step order
RIG_SPRING = [f"y[t-{k}]^3" for k in range(1, 5)]
# The planted families of fixed terms, at lag k.
FIXED_TERMS = {
    "quadratic_stiffness": "y[t-{k}]^2",
    "coulomb_friction": "sign(dy[t-{k}])",
    "quadratic_damping": "dy[t-{k}]*abs(dy[t-{k}])",
}
HERTZ = 1.5  # the exponent of the simulator's Hertzian contact spring
ORIFICE = 0.5  # the exponent of the simulator's power-law (orifice-like) damping
# The input families of one width searched, by their term's function (the width planted is the
# simulator's effect of the family's name less "input_").
INPUT_PLAY = {"input_dead_zone": "deadzone", "input_backlash": "backlash"}


def _with(current: Structure, score: EffectScore) -> Structure:
    if score.noise_lags:
        return replace(current, noise_lags=score.noise_lags)
    return replace(current, terms=current.terms + parse_terms(score.terms))


def _plus(current: Structure, names: list[str]) -> Structure:
    new = [term for term in parse_terms(names) if term not in current.terms]
    return replace(current, terms=current.terms + tuple(new))


def _planted(
    case: Case, current: Structure, checks: CheckSplit, x: np.ndarray, y: np.ndarray, fs: float
) -> list[tuple[str, Structure]]:
    """The planted family with its parameters set or searched on the check blocks' figure."""
    if case.family == "periodic_disturbance":
        f = f"{case.scenario.effects.sine_frequency / fs:.10g}"
        hertz = case.scenario.effects.sine_frequency
        return [(f"sine and cosine at {hertz:g} Hz", _plus(current, [f"sin(2pi*{f}*t)", f"cos(2pi*{f}*t)"]))]
    if case.family == "offset":
        # From a linear start an offset is a constant alone; through the rig's cubic spring it
        # brings the squares too, which only the spring's round can offer.
        squares = [f"y[t-{k}]^2" for k in range(1, 5)]
        constant = "constant (in the start)" if parse_terms(["1"])[0] in current.terms else "constant"
        return [
            (constant, _plus(current, ["1"])),
            ("with the spring and its squares", _plus(current, ["1", *RIG_SPRING, *squares])),
        ]
    if case.family == "hysteresis":
        scale = float(np.std(y))
        levels = np.exp(np.linspace(np.log(0.01 * scale), np.log(10.0 * scale), PROFILE_POINTS))[1:-1]
        shapes = np.linspace(*BOUC_WEN_SHAPES)[1:-1]
        trials = [
            _plus(current, [f"boucwen(y[t-{k}],{w:.4g},{r:.4g})" for k in range(1, 5)])
            for w in levels
            for r in shapes
        ]
        best = min(trials, key=checks.error)
        factor = best.terms[-1].factors[0]
        return [(f"Bouc–Wen, w {factor.parameter:.3g}, r {factor.shape:.3g}", best)]
    if case.family in FIXED_TERMS:
        terms = [FIXED_TERMS[case.family].format(k=k) for k in range(1, 5)]
        return [
            ("at every lag", _plus(current, terms)),
            ("with the spring", _plus(current, [*terms, *RIG_SPRING])),
        ]
    if case.family == "power_law_stiffness":
        exponents = np.linspace(*STIFFNESS_EXPONENTS, PROFILE_POINTS)
        law = ["spow(y[t-" + str(k) + "],{p:.4g})" for k in range(1, 5)]
        return _searched(current, checks, "p", law, exponents, HERTZ)
    if case.family == "power_law_damping":
        exponents = np.linspace(*DAMPING_EXPONENTS, PROFILE_POINTS)
        law = ["spow(dy[t-" + str(k) + "],{p:.4g})" for k in range(1, 5)]
        return _searched(current, checks, "p", law, exponents, ORIFICE)
    if case.family in INPUT_PLAY:
        function = INPUT_PLAY[case.family]
        planted_width = getattr(case.scenario.effects, case.family.removeprefix("input_"))
        scale = float(np.std(x))
        widths = np.exp(np.linspace(np.log(0.01 * scale), np.log(1.5 * scale), PROFILE_POINTS))
        lags = sorted({f.lag for t in current.terms for f in t.factors if f.signal == "x"})
        play = [function + "(x[t-" + str(k) + "],{p:.4g})" for k in lags]
        return _searched(current, checks, "w", play, widths, planted_width)
    raise ValueError(f"no search for {case.family}")


def _searched(
    current: Structure, checks: CheckSplit, name: str, templates: list[str], grid: np.ndarray, planted: float
) -> list[tuple[str, Structure]]:
    """A family of one parameter at its planted value and searched on the check blocks' figure on
    ``grid``, alone and beside the rig's spring (the planted effect is on top of it)."""

    def at(p: float, spring: bool) -> Structure:
        return _plus(current, [t.format(p=p) for t in templates] + (RIG_SPRING if spring else []))

    rows = [(f"at the planted {name} {planted:.3g}", at(planted, False))]
    for spring in (False, True):
        errors = [checks.error(at(p, spring)) for p in grid]
        best = float(grid[int(np.argmin(errors))])
        rows.append((f"{name} {best:.3g}" + (" with the spring" if spring else ""), at(best, spring)))
    return rows


def first_round(
    case: Case, seed: int, samples: int, fold: int = 1
) -> tuple[float, list[tuple[str, float]], float, list[tuple[str, float]]]:
    """The start's check figure on one record, and the falls of that figure, as shares of it:
    the significant families' (the first ``SCORED`` in the one-step order, with their change of
    BIC, and any later one that falls further), the rig's spring's and the planted family's
    searched. ``fold`` picks the check blocks (:func:`models.checking.split_for_checking`): the
    loop's are fold 1's, and the other two show how much a figure owes to which blocks."""
    record = simulate(case.scenario, samples + (TEST if case.periodic else 0), seed)
    x, y = record.x[:samples], record.y[:samples]
    split = held_out_tails([(x, y)])
    assert split is not None
    heads, _ = split
    _, terms = choose_linear(heads, checks=CheckSplit.of(heads))
    checks = CheckSplit.of(heads, fold)
    start = Structure(tuple(terms))
    before = checks.error(start)

    def fall(structure: Structure) -> float:
        return 1 - checks.error(structure) / before

    offered = unused(candidate_effects(terms), terms)
    scores = sorted(
        (s for s in scored(heads, start, offered, DEFAULT_ALPHA, map, map).scores if s.significant),
        key=lambda s: s.bic_change,
    )
    falls = [(f"{s.name} ({s.bic_change:.0f})", fall(_with(start, s))) for s in scores]
    shown = falls[:SCORED]
    later = max(falls[SCORED:], key=lambda named: named[1], default=None)
    if later is not None and later[1] > max(gain for _, gain in shown):
        shown.append(later)
    planted = [(name, fall(s)) for name, s in _planted(case, start, checks, x, y, record.fs)]
    return before, shown, fall(_plus(start, RIG_SPRING)), planted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--samples", type=int, default=SAMPLES)
    parser.add_argument("--only", nargs="+", default=["periodic_disturbance", "hysteresis", "offset"])
    parser.add_argument(
        "--fold", type=int, choices=(0, 1, 2), default=1, help="the check blocks (the loop's: 1)"
    )
    arguments = parser.parse_args()
    console = Console(width=200)
    table = Table(title="The first round's candidates: fall of the check blocks' free run from the start")
    for column in (
        "planted",
        "seed",
        "start",
        "candidates, one-step order",
        "rig's spring",
        "planted, searched",
    ):
        table.add_column(column)
    for case in (c for c in CASES if c.family in arguments.only):
        for seed in range(arguments.first_seed, arguments.first_seed + arguments.seeds):
            before, families, spring, planted = first_round(case, seed, arguments.samples, arguments.fold)
            table.add_row(
                case.family,
                str(seed),
                f"{before:.3g}",
                ", ".join(f"{name} {gain:+.2f}" for name, gain in families),
                f"{spring:+.2f}",
                ", ".join(f"{name}: {gain:+.2f}" for name, gain in planted),
            )
    console.print(table)


if __name__ == "__main__":
    main()
