"""One linear-algebra thread per test worker, as Snakemake gives a ``threads: 1`` job.

Snakemake sets OPENBLAS_NUM_THREADS and OMP_NUM_THREADS to a rule's threads;
pytest does not. Imported first by ``conftest.py``, before numpy loads
OpenBLAS. With two test workers on two cores, two BLAS threads per worker
spin against each other: the geometry stage's centre search (thousands of
small least-squares solves) took 29 s of CPU instead of 19 s for one lens.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
