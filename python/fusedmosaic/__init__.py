"""fusedmosaic: drift-free mosaics of planar scenes from endoscope video fused with an external
pose source (EM tracker or robot).

The C++ core lives in :mod:`fusedmosaic._core`; the Python layer reads datasets
(:mod:`fusedmosaic.io`), simulates them (:mod:`fusedmosaic.simulation`) and scores results
(:mod:`fusedmosaic.evaluation`).
"""

from fusedmosaic import _core

__version__ = "0.1.0"

__all__ = ["_core", "__version__"]
