"""What the test modules share: servers on loopback, API steps, hostile files, the benchmark data.

A package beside the test modules so that no ``test_*.py`` imports another: whatever two test
modules need lives here, and the test modules import only from here (and ``conftest``'s fixtures).
"""
