"""Functions a person can hold in mind: none of the project's is longer than ``LONGEST`` lines.

A long function is read by keeping every part of it in mind at once; one split along its phases,
each a function of what the one before returned, is read a phase at a time. Two kinds are left
whole, for a reason each: a loop compiled by numba (:mod:`models.simulation`), where a call out of
the loop would cost a call a sample, and a migration's schema, a list of tables read one at a time.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "recordfiles", "simulator", "service", "migrations", "bench", "harness", "tests")
LONGEST = 80


def long_functions(root: Path) -> list[str]:
    """Every function under ``root``'s packages longer than ``LONGEST`` lines, docstring and all,
    as ``path:name (lines)``; compiled loops and migrations aside (module docstring)."""
    found = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            relative = path.relative_to(root).as_posix()
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    continue
                lines = node.end_lineno - node.lineno + 1 if node.end_lineno else 0
                compiled = any("numba" in ast.unparse(decorator) for decorator in node.decorator_list)
                if lines > LONGEST and not compiled and not relative.startswith("migrations/versions/"):
                    found.append(f"{relative}:{node.name} ({lines})")
    return found


def test_no_function_is_longer_than_a_person_holds_in_mind() -> None:
    assert long_functions(ROOT) == []


def test_a_long_function_is_found(tmp_path: Path) -> None:
    package = tmp_path / "models"
    package.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(LONGEST))
    (package / "long.py").write_text(
        f"def short():\n    return 1\n\n\ndef long():\n{body}\n", encoding="utf-8"
    )
    assert long_functions(tmp_path) == [f"models/long.py:long ({LONGEST + 1})"]


def test_a_compiled_loop_is_left_whole(tmp_path: Path) -> None:
    package = tmp_path / "models"
    package.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(LONGEST))
    (package / "kernel.py").write_text(f"@numba.njit(cache=True)\ndef kernel():\n{body}\n", encoding="utf-8")
    assert long_functions(tmp_path) == []
