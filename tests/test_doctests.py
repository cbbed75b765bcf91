"""The science's docstring Examples run as written: each module of ``models`` through doctest.

(Here rather than pytest's ``--doctest-modules``, which would import every test module a second
time to look for examples in it.)"""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

MODELS = Path(__file__).resolve().parent.parent / "models"
MODULES = sorted(path.stem for path in MODELS.glob("*.py") if path.stem != "__init__")
# The public science API: each of these modules shows its use in Examples that run.
WITH_EXAMPLES = {"alarms", "fnarx", "inspection", "narx", "novelty", "output_error", "selection", "semp"}


@pytest.mark.parametrize("name", MODULES)
def test_the_examples_of_each_module_hold(name: str) -> None:
    module = importlib.import_module(f"models.{name}")
    failed, tried = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE, report=False)
    assert failed == 0, f"models.{name}: {failed} example(s) do not give what their docstrings show"
    assert tried > 0 or name not in WITH_EXAMPLES, f"models.{name} has lost its Examples"
