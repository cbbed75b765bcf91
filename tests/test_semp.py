"""Structure selection on the simulation error (models.semp) against theory and independent computations.

The system of Piroddi & Spinelli (2003, their first example),

    w[t] = 0.75·w[t−2] + 0.25·x[t−1] − 0.2·w[t−2]·x[t−1],    y[t] = w[t] + v[t],

x uniform on [−1, 1] and v white measurement noise on the output. The noise enters the
equation error as v[t] − 0.75·v[t−2] + 0.2·v[t−2]·x[t−1], coloured and correlated with the
regressors, which FROLS on the one-step error answers with extra terms; the simulation error of
a spurious term's model is no better than the true structure's, so SEMP keeps the three terms.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import signal

from models.candidates import candidate_terms
from models.errors import InputError
from models.narx import NARX, fit_narx
from models.output_error import fit_output_error
from models.selection import select_narx
from models.semp import select_by_simulation
from models.terms import parse_terms, regressor_matrix
from models.validation import validate

TRUE = ("y[t-2]", "x[t-1]", "y[t-2]*x[t-1]")
NOISE = 0.01  # 4.6 % of the output's standard deviation (0.218)


def piroddi(n: int, seed: int, noise: float = NOISE) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, n)
    w = np.zeros(n)
    for t in range(2, n):
        w[t] = 0.75 * w[t - 2] + 0.25 * x[t - 1] - 0.2 * w[t - 2] * x[t - 1]
    return x, w + noise * rng.standard_normal(n)


@pytest.fixture(scope="module")
def dictionary():
    """Degree 3, lags 1–4 of y and x, the constant: 165 candidates."""
    return candidate_terms(3, 4, 4)


def test_simulation_error_finds_the_true_structure_where_frols_adds_terms(dictionary) -> None:
    """On 10 records with output noise FROLS (BIC) never returns the true structure (it adds terms
    to model the coloured equation error); SEMP returns it on every record (measured: 10 of 10;
    with a threshold of 0.5 % instead of the default 2 %, 7 of 10)."""
    records = [piroddi(5000, seed) for seed in range(10)]
    frols = [set(select_narx([record], dictionary).model.term_names) for record in records]
    semp = [select_by_simulation([record], dictionary) for record in records]
    assert sum(terms == set(TRUE) for terms in frols) == 0
    assert all(len(terms) > 3 and set(TRUE) <= terms for terms in frols)
    assert [set(s.model.term_names) for s in semp] == [set(TRUE)] * 10
    for selection in semp:
        assert selection.stopped_by == "no_improvement" and not selection.diverged
        assert [step.action for step in selection.path] == ["start", "add", "add", "add"]
        rms = [step.rms for step in selection.path]
        assert all(later < (1 - 0.02) ** 0.5 * earlier for earlier, later in itertools.pairwise(rms))
        # The last judged free run errs by about the measurement noise (its RMS, 0.01) alone.
        assert NOISE * 0.9 < selection.rms < NOISE * 1.15


OSCILLATOR = ("y[t-1]", "y[t-2]", "x[t-1]", "y[t-1]^3")


def oscillator(n: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A finely sampled hardening oscillator, w[t] = 1.5·w[t−1] − 0.7·w[t−2] + 0.2·x[t−1] − 0.1·w[t−1]³
    (poles of the linear part at 0.75 ± 0.37j), driven by low-pass noise (Butterworth, 0.1 of
    the sampling rate): on such data y[t−1] alone predicts y[t] closely, and the one-step error
    says little about the free run. Returns x, the measured y = w + v, and w."""
    rng = np.random.default_rng(seed)
    b, a = signal.butter(4, 0.2)
    x = 2 * signal.lfilter(b, a, rng.standard_normal(n))
    w = np.zeros(n)
    for t in range(2, n):
        w[t] = 1.5 * w[t - 1] - 0.7 * w[t - 2] + 0.2 * x[t - 1] - 0.1 * w[t - 1] ** 3
    return x, w + noise * rng.standard_normal(n), w


def test_on_finely_sampled_data_the_structure_with_output_error_parameters_simulates_better() -> None:
    """The oscillator with output noise (1.4 % of the output's standard deviation), 6 records.
    FROLS never returns the four true terms (it keeps 11 to 13); SEMP returns them on 3 of 6
    (measured). Least squares biases θ of the true structure (its free run errs by ~4e-3 on
    noise-free validation data, worse than FROLS's larger models at ~8e-4): the structure is
    SEMP's to choose, θ then the output error's (:mod:`models.output_error`). So refined, SEMP's
    model simulates better than FROLS's on 5 of 6 records, by a median factor of 0.45 (measured;
    refining FROLS's models by output error too, SEMP's is still better on 9 of 10 records, by
    a median factor of 0.8, measured once over 10 records: too slow to repeat here)."""
    x_val, _, w_val = oscillator(5000, 999, 0.0)
    exact, ratios = 0, []
    for seed in range(6):
        x, y, _ = oscillator(5000, seed, 0.01)
        candidates = candidate_terms(3, 4, 4)
        frols = select_narx([(x, y)], candidates).model
        semp = select_by_simulation([(x, y)], candidates).model
        assert set(frols.term_names) != set(OSCILLATOR) and len(frols.terms) > 10
        exact += set(semp.term_names) == set(OSCILLATOR)
        refined = fit_output_error(semp, [(x, y)]).model
        rms = [validate(model, [(x_val, w_val)]).free_run.rms for model in (frols, refined)]
        ratios.append(rms[1] / rms[0])
    assert exact >= 3
    assert sum(ratio < 1 for ratio in ratios) >= 5 and np.median(ratios) < 0.6


def _judged_rms(terms: tuple[str, ...], x: np.ndarray, y: np.ndarray, share: float = 0.25) -> float:
    """√J computed independently: numpy's least squares on the equations t ≥ 4 (the dictionary's
    largest lag) of the first (1 − share) of the record, then a free run over the rest from its
    first 4 measured samples, its error over t ≥ 4 of that part."""
    cut = y.size - round(share * y.size)
    parsed = parse_terms(terms)
    Phi, target = regressor_matrix(parsed, x[:cut], y[:cut], lag=4)
    theta = np.linalg.lstsq(Phi, target, rcond=None)[0]
    model = NARX(parsed, theta, np.zeros((len(parsed), len(parsed))))
    run = model.simulate(x[cut:], y[cut:])
    return float(np.sqrt(np.mean((y[cut + 4 :] - run[4:]) ** 2)))


def test_pruning_removes_an_injected_term(dictionary) -> None:
    """Started from the true structure and a spurious term, the first step prunes the spurious
    term: its model's free run is no better than without it. Each J on the path agrees with an
    independent fit and free run to rounding."""
    x, y = piroddi(5000, 0)
    injected = "y[t-1]^2*x[t-3]"
    selection = select_by_simulation([(x, y)], dictionary, start=[*TRUE, injected])
    assert [(step.action, step.term and step.term.name) for step in selection.path] == [
        ("start", None),
        ("prune", injected),
    ]
    assert [term.name for term in selection.removed] == [injected]
    assert selection.model.term_names == list(TRUE)
    start, pruned = selection.path
    assert start.rms == pytest.approx(_judged_rms((*TRUE, injected), x, y), rel=1e-9)
    assert pruned.rms == pytest.approx(_judged_rms(TRUE, x, y), rel=1e-9)
    assert pruned.rms <= (1 + 0.02) ** 0.5 * start.rms


def test_included_terms_are_never_pruned(dictionary) -> None:
    x, y = piroddi(5000, 0)
    injected = "y[t-1]^2*x[t-3]"
    selection = select_by_simulation([(x, y)], dictionary, include=[injected])
    assert selection.model.term_names[0] == injected and set(TRUE) <= set(selection.model.term_names)
    assert injected not in {term.name for term in selection.removed}


def _saturating(x: np.ndarray) -> np.ndarray:
    """w[t] = 0.5·w[t−1] + x[t−1] + 0.3·tanh(w[t−1]²): ≈ 0.3·w² for small w, bounded for large."""
    w = np.zeros(x.size)
    for t in range(1, x.size):
        w[t] = 0.5 * w[t - 1] + x[t - 1] + 0.3 * np.tanh(w[t - 1] ** 2)
    return w


def test_a_candidate_whose_free_run_diverges_is_refused() -> None:
    """Fitted where |y| < 1, y[t−1]² stands for 0.3·tanh(y²) and FROLS takes it; driven by a
    larger positive input, y[t] = 0.5·y + x + 0.3·y² has no fixed point (0.3y² − 0.5y + x = 0
    has no real root for x > 0.21) and its free run diverges, while the system stays below 3.4.
    SEMP, judging on that record, refuses the term."""
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.4, 0.4, 4000)
    y = _saturating(x) + 0.001 * rng.standard_normal(x.size)
    x_judged = rng.uniform(0.0, 1.5, 2000)
    y_judged = _saturating(x_judged)
    candidates = candidate_terms(2, 1, 1, constant=False)
    square = "y[t-1]^2"
    assert square in select_narx([(x, y)], candidates).model.term_names
    with_square = fit_narx([(x, y)], ["y[t-1]", "x[t-1]", square])
    assert np.isnan(with_square.simulate(x_judged, y_judged[:1])).any()  # independent: it diverges
    selection = select_by_simulation([(x, y)], candidates, judged=[(x_judged, y_judged)])
    assert [term.name for term in selection.diverged] == [square]
    assert square not in selection.model.term_names
    assert np.isfinite(selection.rms) and selection.rms < selection.path[0].rms
    assert not np.isnan(selection.model.simulate(x_judged, y_judged[:1])).any()
    with pytest.raises(InputError, match="the free run of the starting terms diverges on the judged data"):
        select_by_simulation(
            [(x, y)], candidates, judged=[(x_judged, y_judged)], start=["y[t-1]", "x[t-1]", square]
        )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"threshold": 1.0}, "threshold must lie in [0, 1)"),
        ({"preselect": 0}, "preselect must be an integer >= 1"),
        ({"max_terms": 0}, "max_terms must be an integer >= 1"),
        ({"judged_share": 0.0}, "the judged share of each record must lie in (0, 1)"),
        ({"include": ["y[t-9]"]}, "included term y[t-9] is not among the candidates"),
        ({"start": ["x[t-7]"]}, "starting term x[t-7] is not among the candidates"),
        ({"start": list(TRUE), "max_terms": 2}, "3 starting terms exceed max_terms = 2"),
        ({"judged": [(np.arange(4.0), np.arange(4.0) ** 2)]}, "judged record 1 has 4 samples"),
    ],
)
def test_bad_settings_are_refused(dictionary, options, message) -> None:
    with pytest.raises(InputError) as error:
        select_by_simulation([piroddi(600, 0)], dictionary, **options)
    assert message in str(error.value)
