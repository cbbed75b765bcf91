"""No module of the project imports itself through others, and importing one changes nothing.

The layering between packages is import-linter's (``[tool.importlinter]`` in pyproject.toml, run
by ``make test``); its acyclic contract compares packages, and this test the modules: a circle of
imports, even one closed inside a function or under ``TYPE_CHECKING``, makes every module on it
load all the others and ties them into one piece that cannot be read, tested or moved alone.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import grimp
import pytest

from models.blas import VARIABLES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["root_packages"]


def import_cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """One circle through each direct import that is on one: the import, then the way back."""
    cycles = []
    for importer in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(importer)):
            back = graph.find_shortest_chain(importer=imported, imported=importer)
            if back is not None:
                cycles.append([importer, *back])
    return cycles


def test_no_module_imports_itself_through_others() -> None:
    graph = grimp.build_graph(*PACKAGES, cache_dir=None)
    assert import_cycles(graph) == []


def test_a_circle_is_found() -> None:
    """The check itself: a circle of three modules is reported, a chain of three is not."""
    graph = grimp.ImportGraph()
    graph.add_import(importer="p.a", imported="p.b")
    graph.add_import(importer="p.b", imported="p.c")
    assert import_cycles(graph) == []
    graph.add_import(importer="p.c", imported="p.a")
    assert ["p.a", "p.b", "p.c", "p.a"] in import_cycles(graph)


# A command whose module loads numpy: `narxwatch --help` would load every command's, seconds more.
@pytest.mark.parametrize(
    ("entry_point", "args"), [("service.cli", ["simulate", "--help"]), ("simulator.client", ["--help"])]
)
@pytest.mark.parametrize(("given", "expected"), [({}, "1 1 1"), ({"OPENBLAS_NUM_THREADS": "3"}, "3 1 1")])
def test_the_entry_points_ask_for_one_blas_thread_before_numpy_loads(entry_point, args, given, expected):
    """Importing the packages sets nothing and loads no numpy; the console scripts' ``main`` sets
    one thread for each BLAS the user left alone, before a command loads numpy (BLAS reads the
    variables then, once). In a fresh process, as a console script starts."""
    child = textwrap.dedent(f"""
        import os, sys
        import models, recordfiles, service, simulator, {entry_point}
        assert not set({VARIABLES!r}) - set({list(given)!r}) & set(os.environ), "an import set them"
        assert "numpy" not in sys.modules, "numpy loaded before main could set the threads"
        sys.argv = ["main", *{args!r}]
        try:
            {entry_point}.main()
        except SystemExit:
            pass
        assert "numpy" in sys.modules
        print(*(os.environ[variable] for variable in {VARIABLES!r}), file=sys.stderr)
    """)
    env = {name: value for name, value in os.environ.items() if name not in VARIABLES} | given
    run = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr.strip().splitlines()[-1] == expected


# scipy's submodules the science uses in a few functions each, which scipy loads on first use
# (``scipy.signal.lfilter``): with what they import in turn (interpolate, sparse, …), the most of
# scipy a process can start without.
ON_USE = ("scipy.signal", "scipy.stats", "scipy.optimize", "scipy.ndimage", "scipy.fft", "scipy.io")


def test_the_service_s_processes_start_without_the_scipy_they_load_on_use():
    """`narxwatch serve` (its app, as each uvicorn worker imports it) and `narxwatch worker` (both
    job backends) import the whole service and the science it names, but none of ``ON_USE``: a
    process that never filters a signal, designs a chart or reads a MAT file does not load them.
    In a fresh process, as each starts."""
    child = textwrap.dedent(f"""
        import sys
        import service.api.app, service.cli.server, service.jobs.embedded, service.jobs.distributed
        assert "models.inspection" in sys.modules and "scipy.linalg" in sys.modules
        print(*sorted(set({ON_USE!r}) & set(sys.modules)))
    """)
    run = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == []


def test_the_simulation_commands_start_without_numba_or_scipy():
    """`narxwatch-sim` (every command: its options name the simulator's scenarios) and `narxwatch
    simulate` load neither numba (models.terms, for backlash alone) nor scipy (the chain's
    natural frequencies alone) at start; the test suite and a demonstration start many of them.
    In a fresh process, as each starts."""
    child = textwrap.dedent("""
        import sys
        import simulator.client.commands, service.cli.simulate
        print(*sorted(name for name in sys.modules if name.split(".")[0] in ("numba", "scipy")))
    """)
    run = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == []
