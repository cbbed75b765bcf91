"""narxwatch's service layer: the command line now, the REST API and jobs next.

The regressions here are tall and thin (tens of thousands of rows, tens of columns): a
multi-threaded BLAS gains nothing on them and, on a busy machine, its threads contend and
run several times slower. narxwatch's processes therefore use one BLAS thread each and scale
by processes; a user who wants otherwise sets OPENBLAS_NUM_THREADS (or the OMP/MKL ones).
This must run before numpy is first imported, which is why it lives in the package's init.
"""

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")
