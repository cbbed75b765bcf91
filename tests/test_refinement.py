"""The refinement loop: the missing effect is found, named, and the held-out error falls."""

from __future__ import annotations

import numpy as np
import pytest
import statsmodels.api as sm

from models.errors import InputError
from models.refinement import candidate_effects, linear_terms, refine
from models.terms import max_lag, parse_terms, regressor_matrix
from models.validation import validate
from simulator.recordfile import parse_silverbox
from simulator.simulate import Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS

ESTIMATION, HELD_OUT = 8000, 4000
# Official Silverbox split (shared/data/README.md); each test run starts from 50 measured outputs.
SILVERBOX_ESTIMATION = slice(40650, 105712)
SILVERBOX_ARROW = slice(100, 40575)
SILVERBOX_INITIAL = 50


def paper_record(effects: list[str], seed: int, disturbance_std: float = 200.0):
    scenario = Scenario(disturbance_std=disturbance_std, effects=Effects.parse(effects))
    record = simulate(scenario, ESTIMATION + HELD_OUT, seed)
    return record.x, record.y


def held_out_errors(model, x, y, initial: int = 0):
    """Errors on a held-out stretch whose first ``initial`` samples only start the model."""
    start = max(initial - model.max_lag, 0)
    return validate(model, [(x[start:], y[start:])])


@pytest.fixture(scope="module")
def silverbox(silverbox_dir):
    return parse_silverbox((silverbox_dir / "SNLS80mV.csv").read_bytes())


def test_silverbox_from_linear_arx_finds_the_cubic_stiffness_and_the_offset(silverbox):
    x, y = silverbox.x, silverbox.y
    result = refine(x[SILVERBOX_ESTIMATION], y[SILVERBOX_ESTIMATION], linear_terms(4, 4))
    names = [effect.name for effect in result.effects_added]
    assert "cubic_stiffness" in names and "offset" in names, names
    test_x, test_y = x[SILVERBOX_ARROW], y[SILVERBOX_ARROW]
    before = held_out_errors(result.declared, test_x, test_y, SILVERBOX_INITIAL).free_run.rms
    after = held_out_errors(result.refined, test_x, test_y, SILVERBOX_INITIAL).free_run.rms
    assert before > 10e-3, f"linear ARX free run {before * 1e3:.2f} mV"
    assert after <= 2.5e-3, f"refined free run {after * 1e3:.2f} mV"


def test_quadratic_stiffness_is_found_first_and_the_one_step_error_halves():
    x, y = paper_record(["quadratic_stiffness2=3e5"], seed=1)
    result = refine(x[:ESTIMATION], y[:ESTIMATION], EXACT_TERMS)
    assert result.effects_added[0].name == "quadratic_stiffness"
    before = held_out_errors(result.declared, x[ESTIMATION:], y[ESTIMATION:]).one_step.rms
    after = held_out_errors(result.refined, x[ESTIMATION:], y[ESTIMATION:]).one_step.rms
    assert after <= before / 2, (before, after)


def test_on_clean_data_no_effect_is_added_in_at_least_95_of_100_runs():
    added = 0
    for seed in range(100):
        x, y = paper_record([], seed=1000 + seed, disturbance_std=800.0)
        added += bool(refine(x[:ESTIMATION], y[:ESTIMATION], EXACT_TERMS).effects_added)
    assert added <= 5, f"an effect was added to {added} of 100 clean records"


def test_score_and_f_statistic_agree_with_refitting_by_statsmodels():
    x, y = paper_record(["quadratic_stiffness2=3e5"], seed=2)
    x, y = x[:ESTIMATION], y[:ESTIMATION]
    first = refine(x, y, EXACT_TERMS, max_rounds=1).rounds[0]
    assert first.added is not None
    declared = parse_terms(EXACT_TERMS)
    lag = max(max_lag(e.terms) for e in candidate_effects(declared))
    lag = max(lag, max_lag(declared))
    Phi, target = regressor_matrix(declared, x, y, lag)
    extra, _ = regressor_matrix(parse_terms(first.added.terms), x, y, lag)
    scale = np.linalg.norm(np.hstack([Phi, extra]), axis=0)
    restricted = sm.OLS(target, Phi / scale[: Phi.shape[1]]).fit()
    full = sm.OLS(target, np.hstack([Phi, extra]) / scale).fit()
    assert first.added.explained == pytest.approx(1 - full.ssr / restricted.ssr, rel=1e-6)
    one_term = sm.OLS(target, np.hstack([Phi, extra[:, :1]]) / scale[: Phi.shape[1] + 1]).fit()
    f_value, p_value, _ = one_term.compare_f_test(restricted)
    assert first.added.f_statistics[0] == pytest.approx(f_value, rel=1e-6)
    assert first.added.p_values[0] == pytest.approx(p_value, rel=1e-6, abs=1e-300)
    assert first.level == pytest.approx(0.01 / first.candidates)


def test_candidate_effects_leave_out_terms_the_model_has():
    declared = parse_terms(["y[t-1]", "y[t-2]", "y[t-1]^3", "x[t-1]", "1"])
    effects = {effect.name: effect for effect in candidate_effects(declared)}
    assert "offset" not in effects  # the constant is declared already
    assert "y[t-1]^3" not in [t.name for t in effects["cubic_stiffness"].terms]
    assert [t.name for t in effects["missing_lags"].terms] == ["y[t-3]", "y[t-4]", "x[t-2]", "x[t]"]


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: linear_terms(0, 2), "ny >= 1"),
        (lambda: linear_terms(2, 2, delay=-1), "delay >= 0"),
        (lambda: refine(np.ones(100), np.ones(100), ["y[t-1]"], alpha=1.5), "alpha"),
    ],
)
def test_bad_arguments_are_refused_clearly(call, message):
    with pytest.raises(InputError, match=message):
        call()
