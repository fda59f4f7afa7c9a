"""pregrasp's application layer: the command line (``app.cli``) and the viser inspection app.

Importing ``app`` (which the ``pregrasp`` console script does first) limits the BLAS/OpenMP
thread pools to one thread unless the environment already says otherwise. The core's matrix
products are tiny ((N, 3) x (3, 3)); OpenBLAS spreading them over threads made a 20,000-point
decomposition three times slower on a 2-core machine (156 ms against 52 ms, see
``docs/benchmarks.md``), and the viewer's server threads compete for the same cores. The
variables only take effect when numpy has not been imported yet, as in the console script.
"""

import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
