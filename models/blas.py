"""One BLAS thread a process: what narxwatch's entry points ask for before numpy is imported.

The regressions here are tall and thin (tens of thousands of rows, tens of columns): a
multi-threaded BLAS gains nothing on them and, on a busy machine, its threads contend and run
several times slower. narxwatch's processes therefore use one BLAS thread each and scale by
processes; a user who wants otherwise sets OPENBLAS_NUM_THREADS (or the OMP/MKL ones).
"""

from __future__ import annotations

import os

VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread() -> None:
    """One thread for each BLAS whose variable the user left unset. A call, not an import's side
    effect: BLAS reads the variables once, when numpy first loads it, so each entry point calls
    this before it imports numpy; processes it starts (uvicorn's workers, ``narxwatch worker``'s
    children) inherit the environment."""
    for variable in VARIABLES:
        os.environ.setdefault(variable, "1")
