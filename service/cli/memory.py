"""Freed memory kept for the next array: what ``narxwatch refine`` asks of its process.

The refinement loop makes and drops arrays of one to tens of megabytes thousands of times (each
round's candidate columns and their projections off the model, the bases of their spans, the
output-error Jacobians). glibc's malloc returns a block that large to the kernel as it is freed
(a mapping of its own, or the heap's top trimmed), so the next array of that size has every page
faulted in and zeroed again; and numpy asks the kernel to back arrays of 4 MB or more with huge
pages, which on a machine whose memory is fragmented sends each of those faults into compaction.
That is system time, none of it arithmetic: every figure stays the same to the bit. A command
that owns its process takes it; the service's long-lived workers, shared by every organisation,
do not: they hand back memory that a finished job no longer needs.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

# mallopt's parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# Blocks up to glibc's largest threshold (half its heap size on 64 bits) come from the heap, where
# a freed block is reused; larger ones are still mapped and returned as they are freed.
MMAP_THRESHOLD = 32 * 2**20
# Free memory the heap keeps at its top rather than handing back: the loop's working set, many
# times over.
TRIM_THRESHOLD = 2**30


def hold_freed_memory() -> bool:
    """Keep freed arrays' memory in the process for the next ones, and back numpy's arrays with
    ordinary pages. A call for a command that owns its process, not an import's side effect: the
    settings are the process's and its forked workers'. Returns whether malloc took them (glibc's
    only; elsewhere the allocator is left as it is)."""
    # numpy's switch for its huge-page advice (its documentation's "global state";
    # NUMPY_MADVISE_HUGEPAGE is read only as numpy loads, before a command's arguments are known).
    advise = getattr(np._core.multiarray, "_set_madvise_hugepage", None)
    if advise is not None:
        advise(False)
    if not _glibc():
        return False
    mallopt = ctypes.CDLL(None).mallopt
    # Both: setting either ends glibc's own adjustment of the two (each raised as large blocks
    # are freed) and leaves the other at its default of 128 kB.
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def _glibc() -> bool:
    """Whether this process's C library is glibc, whose malloc :func:`hold_freed_memory` tunes."""
    try:
        return os.confstr("CS_GNU_LIBC_VERSION") is not None
    except (ValueError, OSError):  # a platform without the name, or a C library without it
        return False
