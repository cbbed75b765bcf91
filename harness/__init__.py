"""What the tests and the benchmarks share to run narxwatch for real and talk to it.

Servers on loopback (``postgres``, ``live``, ``workers``, ``receivers``); the API's steps
(``api_helpers``, ``channel_helpers``, ``dashboard_helpers``, ``job_helpers``, ``estates``) and
the console script (``cli``); records and what to check them against (``multisines``,
``accelerometer``, ``fleet``); hostile files (``mat_bombs``, ``npz_bombs``); what a test needs
from outside the repository (``prerequisites``); and numba's kernels compiled into their cache
before the suite runs (``kernels``). A package of its own, beside ``tests/`` and
``bench/``: no test module imports another, and no benchmark reaches into ``tests/``. Not part of
the installed distribution (pyproject's wheel lists the product's packages).
"""
