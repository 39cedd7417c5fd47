"""Suite-wide settings.

Small BLAS calls on OpenBLAS's spinning threads ran ~35x slower on the 2-core CI
machine when other work competed for the cores; one BLAS thread per process is faster
for every test here (the heavy kernels use numba or Dr.Jit threads, not BLAS). The
variables must be set before NumPy loads OpenBLAS, hence at conftest import time (the
Makefile sets them too).
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
