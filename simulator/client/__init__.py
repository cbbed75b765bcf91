"""``narxwatch-sim``: simulated records posted to a running narxwatch service, or written to files.

``narxwatch simulate`` writes one file; this command feeds a service the way a data-acquisition
system would (one record, the paper's four test cases, or a timed stream) and prints each verdict
on one line, so that a demonstration or a smoke test of a deployment needs only a URL and a key.
It reaches the service over HTTP alone, like any other client. The scenario options are those of
``narxwatch simulate``: same names, defaults and messages.

Every record's seed is printed (or written to the manifest), so any record can be made again with
``narxwatch simulate --seed``. Output goes to stdout, one line per record; commentary and errors go
to stderr, so that ``--json`` output stays one JSON document a line.

The package: the HTTP client (:mod:`~simulator.client.http`), which records to make and when
(:mod:`~simulator.client.scheduler`), where they go (:mod:`~simulator.client.destinations`) and
the commands with their options (:mod:`~simulator.client.commands`).
"""

from __future__ import annotations

from models.blas import one_blas_thread


def main() -> None:
    """Console-script entry point (``narxwatch-sim``); :func:`simulator.client.commands.run`."""
    # Before the commands load numpy, which is why they are imported here.
    one_blas_thread()
    from simulator.client.commands import run

    run()
