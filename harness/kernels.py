"""numba's kernels of models/, compiled once into their cache before the suite runs.

Each kernel is compiled on its first call in a process and cached beside its source
(``cache=True``); a process that finds it there loads it instead. In a fresh clone no process
does: both pytest-xdist processes of ``make test`` start with science files and would compile the
same kernels at once, and each ``narxwatch`` process a test starts before them again. ``make test``
runs this module while the site is built and the linters run (``python -m harness.kernels``): a
small fit calls every kernel once with the argument types narxwatch calls it with, and a kernel
that none of these calls reaches is named, so that a new one is added here rather than compiled
in every process of a fresh clone again.
"""

from __future__ import annotations

import importlib
import pkgutil

import numba
import numpy as np

import models
from models.narx import fit_narx
from models.output_error import estimated_start_error, fit_output_error
from models.regression import subtract_outer
from models.simulation import FreeRun
from models.terms import bouc_wen, parse_terms, play

SAMPLES = 400


def kernels() -> dict[str, numba.core.registry.CPUDispatcher]:
    """Every kernel of models/ that is compiled on its own, by qualified name: those inlined where
    they are called (``inline="always"``) are compiled with their caller."""
    found = {}
    for module_info in pkgutil.iter_modules(models.__path__, "models."):
        module = importlib.import_module(module_info.name)
        for name, value in vars(module).items():
            if (
                isinstance(value, numba.core.registry.CPUDispatcher)
                and value.__module__ == module.__name__
                and value.targetoptions.get("inline", "never") != "always"
            ):
                found[f"{module.__name__}.{name}"] = value
    return found


def compile_kernels() -> None:
    """Call every kernel through the code that calls it: a second-order ARX fitted by least
    squares, refined by its free run's error (the free run and its sensitivities, MINPACK's
    search, the estimated start), and the effects' own kernels."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal(SAMPLES)
    y = np.zeros(SAMPLES)
    for t in range(2, SAMPLES):
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + x[t - 1] + 0.01 * rng.standard_normal()
    model = fit_narx([(x, y)], ["y[t-1]", "y[t-2]", "x[t-1]"])
    fit_output_error(model, [(x, y)], max_evaluations=5)
    estimated_start_error(model, x, y)
    FreeRun.build(parse_terms(["y[t-1]", "x[t-1]"]), x).run_with_sensitivities(np.array([0.5, 1.0]), y[:1])
    subtract_outer(np.ones((3, 2)), np.ones(3), np.ones(2))
    bouc_wen(x, 1.0, 1.0)
    play(x, 0.1)


def cached(kernel: numba.core.registry.CPUDispatcher) -> bool:
    """Whether ``kernel`` is compiled in this process or in its cache: a kernel called only by
    other kernels is not compiled where its callers are loaded from the cache (numba keeps no
    public account of the cache's contents: its index is read as numba reads it)."""
    return bool(kernel.signatures) or bool(kernel._cache._cache_file._load_index())


def main() -> None:
    compile_kernels()
    missed = sorted(name for name, kernel in kernels().items() if not cached(kernel))
    if missed:
        raise SystemExit(
            f"harness/kernels.py compiles none of {', '.join(missed)}: call them in compile_kernels"
        )


if __name__ == "__main__":
    main()
