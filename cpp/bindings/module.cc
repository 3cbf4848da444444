// The fusedmosaic._core extension: one module, one Bind<Domain>() per domain.
#include <pybind11/pybind11.h>

#include "bindings/bind.h"

PYBIND11_MODULE(_core, m) {
  m.doc() = "fusedmosaic C++ core: plane-induced geometry and Ceres solvers.";
#ifdef FUSEDMOSAIC_VERSION
  m.attr("__version__") = FUSEDMOSAIC_VERSION;
#endif
  fusedmosaic::bindings::BindGeometry(m);
  fusedmosaic::bindings::BindResiduals(m);
  fusedmosaic::bindings::BindProblem(m);
  fusedmosaic::bindings::BindSlidingWindow(m);
  fusedmosaic::bindings::BindRegistration(m);
}
