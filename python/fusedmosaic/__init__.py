"""fusedmosaic: drift-free mosaics of planar scenes from endoscope video fused with an external
pose source (EM tracker or robot).

The C++ core lives in :mod:`fusedmosaic._core`; the Python layer reads datasets
(:mod:`fusedmosaic.io`), simulates them (:mod:`fusedmosaic.simulation`) and scores results
(:mod:`fusedmosaic.evaluation`). The two streaming mosaickers, for live loops, are exported here:
:class:`SequentialMosaicker` (EM tracker, LBAVis+EMT) and :class:`RobotPriorMosaicker` (robot
prior, pCLE).
"""

from __future__ import annotations

import importlib
import typing

__version__ = "0.1.0"

__all__ = ["RobotPriorMosaicker", "RobotPriorOptions", "SequentialMosaicker",
           "SequentialOptions", "_core", "__version__"]

# Imported on first use (PEP 562), so that the command line's entry (fusedmosaic._entry) runs
# before NumPy, OpenCV and the core load, and a Ctrl-C while they do ends it cleanly.
_LAZY = {"_core": ("fusedmosaic._core", None),
         "SequentialMosaicker": ("fusedmosaic.estimation.sequential", "SequentialMosaicker"),
         "SequentialOptions": ("fusedmosaic.estimation.sequential", "SequentialOptions"),
         "RobotPriorMosaicker": ("fusedmosaic.estimation.translation", "RobotPriorMosaicker"),
         "RobotPriorOptions": ("fusedmosaic.estimation.translation", "RobotPriorOptions")}

if typing.TYPE_CHECKING:
    from fusedmosaic import _core
    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
    from fusedmosaic.estimation.translation import RobotPriorMosaicker, RobotPriorOptions


# Subpackages reachable as attributes (fusedmosaic.io, ...), as when __init__ imported them.
_SUBMODULES = ("cli", "compositing", "estimation", "evaluation", "io", "methods",
               "registration", "runner", "simulation")


def __getattr__(name: str):
    if name in _SUBMODULES:
        module, attribute = f"fusedmosaic.{name}", None
    elif name in _LAZY:
        module, attribute = _LAZY[name]
    else:
        raise AttributeError(f"module 'fusedmosaic' has no attribute {name!r}")
    value = importlib.import_module(module)
    if attribute is not None:
        value = getattr(value, attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
