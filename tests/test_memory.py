"""``narxwatch refine`` keeps freed arrays' memory for the next ones (service.cli.memory): the
loop's arrays of megabytes are made and dropped thousands of times, and each one made afresh
costs its pages' faults. Each check runs in a fresh process, whose allocator it may change."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from service.cli.memory import _glibc

# Arrays of the loop's sizes (candidate columns and a basis of their span over 52 000 rows) made
# and dropped; the page faults of one round of them, counted after a first round has warmed up.
ROUNDS = textwrap.dedent("""
    import resource
    import numpy as np
    {setup}
    def churn():
        a = np.ones((52000, 40))
        b = a * 2
        c = np.ones((52000, 10))
        del a, b, c
    churn()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        churn()
    print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
""")


def faults(setup: str) -> float:
    """The page faults of a round, counted in pages of 4 kB: numpy's huge-page advice is off in
    both processes (a huge page is one fault for 2 MB)."""
    env = os.environ | {"NUMPY_MADVISE_HUGEPAGE": "0"}
    child = ROUNDS.format(setup=setup)
    run = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return float(run.stdout)


@pytest.mark.skipif(not _glibc(), reason="the allocator tuned is glibc's")
def test_freed_arrays_memory_is_reused_without_faulting_it_in_again() -> None:
    # 40 MB a round: by default about ten thousand pages faulted in again (each 4 kB zeroed by the
    # kernel); held, only what numpy's small allocations reach beyond the heap.
    default = faults("")
    held = faults("from service.cli.memory import hold_freed_memory\nassert hold_freed_memory()")
    assert default > 5000
    assert held < default / 10


def test_the_refine_command_holds_freed_memory() -> None:
    """The command sets it for its process (and the workers it forks), before reading a file: here
    seen by numpy's huge-page advice, off after the command (on by default where the kernel
    offers huge pages). Through the console script's ``main``, in a fresh process."""
    child = textwrap.dedent("""
        import sys
        import service.cli
        sys.argv = ["narxwatch", "refine", "/nonexistent.csv"]
        try:
            service.cli.main()
        except SystemExit as exit:
            assert exit.code, "a missing file is refused"
        import numpy as np
        print(np._core.multiarray._get_madvise_hugepage())
    """)
    run = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[-1] == "False"
