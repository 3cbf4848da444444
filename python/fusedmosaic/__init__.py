"""fusedmosaic: drift-free mosaics of planar scenes from endoscope video fused with an external
pose source (EM tracker or robot).

The C++ core lives in :mod:`fusedmosaic._core`; the Python layer reads datasets
(:mod:`fusedmosaic.io`), simulates them (:mod:`fusedmosaic.simulation`) and scores results
(:mod:`fusedmosaic.evaluation`). The two streaming mosaickers, for live loops, are exported here:
:class:`SequentialMosaicker` (EM tracker, LBAVis+EMT) and :class:`RobotPriorMosaicker` (robot
prior, pCLE).
"""

from fusedmosaic import _core
from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
from fusedmosaic.estimation.translation import RobotPriorMosaicker, RobotPriorOptions

__version__ = "0.1.0"

__all__ = ["RobotPriorMosaicker", "RobotPriorOptions", "SequentialMosaicker",
           "SequentialOptions", "_core", "__version__"]
