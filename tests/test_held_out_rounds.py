"""The rounds' models judged against each other on the held-out tails (models/rounds_on_tails.py): a
round that made the model worse there is set aside, where the gate compares only the final model
with the start."""

from __future__ import annotations

import numpy as np

from models.checking import free_run_rms
from models.held_out import held_out_tails
from models.narx import fit_narx
from models.output_error import diverged
from models.refinement import refine
from models.terms import Term
from simulator.simulate import Effects, Scenario, simulate


def test_a_last_round_that_ran_free_worse_over_the_tails_is_set_aside():
    """The rig with a quadratic spring, nothing declared, 1600 samples (seed 8012). The rounds name
    the cubic and the square, then a Bouc–Wen variable of the stiffening class (β + γ < 0), which
    the check blocks approved and which grows without bound with the output's excursion: over
    the tails the model with it ran free worse than the model without, and over a record from
    another seed, which leaves the estimation record's range, it diverged. The model returned
    runs free over the tails no worse than each round's model, fitted here by least squares on
    the heads as the rounds fitted them, holds no hysteresis, and stays bounded on that record."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["quadratic_stiffness2=3e5"]))
    record, other = simulate(scenario, 1600, seed=8012), simulate(scenario, 2000, seed=58012)
    result = refine([(record.x, record.y)], None)
    held_out = result.held_out
    assert held_out is not None and held_out.kept
    split = held_out_tails([(record.x, record.y)])
    assert split is not None
    heads, tails = split
    terms = list(result.declared.terms)
    by_round = []
    for step in result.rounds:
        if step.added is not None and not step.added.noise_lags:
            terms += [Term.parse(name) for name in step.added.terms]
            by_round.append(free_run_rms(fit_narx(heads, terms), tails, heads))
    assert len(by_round) >= 3, [step.added for step in result.rounds]
    assert held_out.refined_rms <= min(by_round) * (1 + 1e-9), (held_out.refined_rms, by_round)
    assert "hysteresis" not in [effect.name for effect in result.effects_added]
    assert held_out.set_aside == ("hysteresis",)
    returned = result.refined
    run = returned.simulate(other.x, other.y[: returned.max_lag])
    assert np.all(np.isfinite(run)) and not diverged(run, other.y)
