"""v2v: multi-vehicle V2V collaborative relative-positioning simulator.

Pipeline (dependencies point one way)::

    traffic (libsumo) -> world/sensors -> exchange -> estimation -> metrics -> viz

Units are SI and angles radians inside the package; degrees appear only at the
input/output edge (scenario fields named ``*_deg``, printed tables).
"""

import os as _os

# v2v's linear algebra is many small matrices (per-vehicle blocks, scalar updates). A
# multi-threaded BLAS makes those 10-100x slower on a busy machine (measured: scipy expm
# of a 16x16 matrix, 13 ms with OpenBLAS threads vs 0.08 ms with one). Sweeps run one
# process per core instead. Set before numpy loads; a user's explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
