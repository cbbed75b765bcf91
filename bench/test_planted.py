"""bench/planted.py's reading of a refinement: which effect counts as named first."""

from __future__ import annotations

from bench.planted import CASES, RIG_SPRING, Run


def run_naming(family: str, *named: str) -> Run:
    case = next(i for i, c in enumerate(CASES) if c.family == family)
    return Run(case, 1600, 0, named, (4, 4, 1), 1.0, 1.0, 0.0)


def test_the_planted_effect_after_the_rigs_spring_entered_over_two_rounds_counts_as_after_it() -> None:
    """Seed 8313 at 1600 samples: the rig's spring took rounds 1 and 2 (more of its lags), the
    quadratic spring round 3; the spring set aside, the planted effect is the first named."""
    run = run_naming("quadratic_stiffness", RIG_SPRING, RIG_SPRING, "quadratic_stiffness")
    assert run.first_but_the_spring and not run.first
    assert not run_naming(
        "quadratic_stiffness", RIG_SPRING, "offset", "quadratic_stiffness"
    ).first_but_the_spring
    assert not run_naming("quadratic_stiffness", RIG_SPRING, RIG_SPRING).first_but_the_spring
