"""The refinement protocol that ``narxwatch refine`` and the API share (models.refinement_protocol):
on parts of one record, each validation record judged whole after its transient; on either
protocol, the effects explained on the first record judged, and each test named as the caller
names it. Short records: the CLI and API tests run the protocol end to end."""

from __future__ import annotations

import numpy as np
import pytest

from models.explanation import explain_refinement
from models.refinement import compare
from models.refinement_protocol import Loop, default_split, refine_parts, refine_whole
from simulator.simulate import Scenario, simulate
from simulator.theory import EXACT_TERMS

TRANSIENT = 50


@pytest.fixture(scope="module")
def records():
    """A record and a validation record of the rig, short enough for a quick loop."""
    return [simulate(Scenario(disturbance_std=200.0), 600, seed=seed) for seed in (3, 4)]


def test_the_default_split_fits_two_thirds_and_judges_the_last():
    assert default_split(600) == ((0, 400), (400, 600))
    assert default_split(100) == ((0, 66), (66, 100))


def test_parts_judge_each_validation_record_whole_after_its_transient_and_explain_the_test_part(records):
    record, validation = records
    stages: list[str] = []
    loop = Loop(EXACT_TERMS, initial=4, fs=record.fs, transient=TRANSIENT, progress=stages.append)
    refined = refine_parts(
        loop, record.x, record.y, [(0, 496)], (496, 600), [(validation.x, validation.y)], ["v"]
    )
    report, result = refined.report, refined.report.refinement
    assert len(report.tests) == 2 and "judging both models on v" in stages
    fitted = [(record.x[:496], record.y[:496])]
    whole = compare(result, fitted, validation.x, validation.y, 4, record.fs, 0, TRANSIENT)
    assert report.tests[1].after.free_run_rms == whole.after.free_run_rms
    assert report.tests[1].before.one_step_rms == whole.before.one_step_rms
    # Scored after the transient: the record judged from its first sample differs.
    from_start = compare(result, fitted, validation.x, validation.y, 4, record.fs, 0, 0)
    assert report.tests[1].after.free_run_rms != from_start.after.free_run_rms
    np.testing.assert_array_equal(refined.explained[1], record.y[496:600])
    expected = explain_refinement(result, record.x[496:600], record.y[496:600], 4, 496)
    assert refined.explanation.to_dict() == expected.to_dict()


def test_whole_records_explain_the_first_test_after_its_transient_and_name_each_test(records):
    record, validation = records
    loop = Loop(EXACT_TERMS, initial=4, fs=record.fs, transient=TRANSIENT)
    refined = refine_whole(loop, [(record.x, record.y)], [(validation.x, validation.y)])
    expected = explain_refinement(refined.report.refinement, validation.x, validation.y, 4, 0, TRANSIENT)
    assert refined.explanation.to_dict() == expected.to_dict()
    document = refined.to_dict([{"record_id": 7, "samples": [TRANSIENT, 600]}])
    (test,) = document["tests"]
    assert test["record_id"] == 7 and test["samples"] == [TRANSIENT, 600] and "verdict" in test
    assert document["explanation"] == expected.to_dict()
    with pytest.raises(ValueError):
        refined.to_dict([])  # every test named, or none


def test_parts_around_a_glitch_refine_as_the_record_without_it():
    """Estimation parts are fitted as records of their own, no lag reaching across the gap between
    them: a glitch left out between two parts changes nothing of the refinement or of its report.
    (The CLI's and the API's tests check that the parts they are given reach the loop.)"""
    record = simulate(Scenario(disturbance_std=200.0), 1200, seed=5)
    glitched = record.y.copy()
    glitched[400] = 10 * np.abs(record.y).max()
    loop = Loop(EXACT_TERMS, fs=record.fs)
    parts, test = [(0, 390), (410, 800)], (800, 1200)
    around, clean = (refine_parts(loop, record.x, y, parts, test) for y in (glitched, record.y))
    assert around.report.to_dict() == clean.report.to_dict()
    assert around.explanation.to_dict() == clean.explanation.to_dict()
