"""What some tests need from outside the repository, and what happens when it is not there.

The measured benchmark data sets live in ``../shared/data`` beside the clone (or
``$NARXWATCH_DATA_DIR``), never in the repository, and Chromium comes from
``scripts/ensure-chromium.sh``. A clone of the repository alone skips the tests that need them,
each saying what is missing; with ``CI=true`` they fail instead, as a missing PostgreSQL does
(``postgres.in_ci``): CI must run them.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NoReturn

from harness.postgres import in_ci

DATA_DIR = Path(os.environ.get("NARXWATCH_DATA_DIR", Path(__file__).resolve().parents[2] / "shared" / "data"))
SILVERBOX_SHA256 = {
    "SNLS80mV.csv": "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1",
    "Schroeder80mV.csv": "b22cbcba9c59d9b4b1b379967b669dc32959e515b24784da3254505f8563e36c",
}


def unavailable(message: str) -> NoReturn:
    """Skip the test for want of ``message``'s prerequisite; with ``CI=true``, fail it."""
    import pytest  # here: the benchmark scripts read DATA_DIR without a test run

    if in_ci():
        pytest.fail(f"CI=true and {message}")
    pytest.skip(message)


def benchmark_data(folder: str, *names: str) -> Path:
    """``DATA_DIR/folder``, which must hold ``names``: else the test is ``unavailable``, naming them."""
    path = DATA_DIR / folder
    missing = [name for name in names if not (path / name).is_file()]
    if missing:
        unavailable(
            f"benchmark data missing: {', '.join(missing)} in {path} (the measured benchmark data sets "
            "of ../shared/data, described in its README.md; set NARXWATCH_DATA_DIR to where they are)"
        )
    return path


def benchmark_file(folder: str, name: str) -> Path:
    """The path of one benchmark file (see ``benchmark_data``)."""
    return benchmark_data(folder, name) / name
