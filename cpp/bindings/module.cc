// The fusedmosaic._core extension: one module, one Bind<Domain>() per domain.
#include <glog/logging.h>
#include <pybind11/pybind11.h>

#include <cstdlib>

#include "bindings/bind.h"

PYBIND11_MODULE(_core, m) {
  m.doc() = "fusedmosaic C++ core: plane-induced geometry and Ceres solvers.";
  // Ceres reports trouble it recovers from through glog at WARNING, e.g. a Levenberg-Marquardt
  // step whose linear solve failed ("CHOLMOD warning: Matrix not positive definite"), retried
  // with more damping: a tracker contradicting the images printed 341 such lines, and glog's
  // "Logging before InitGoogleLogging()", on stderr. What matters of a solve is in its summary
  // (warned of in report.json). So do its errors: a window step whose evaluation failed
  // printed "Terminating: Residual and Jacobian evaluation failed." on every failed step of a
  // live loop; the failure is in the step's summary (termination, message), which the callers
  // act on and report. Left alone when the host set glog's level (GLOG_minloglevel in the
  // environment, e.g. 0 to see everything, 2 errors only; or FLAGS_minloglevel != 0).
  if (std::getenv("GLOG_minloglevel") == nullptr && FLAGS_minloglevel == 0) {
    FLAGS_minloglevel = google::GLOG_FATAL;
  }
#ifdef FUSEDMOSAIC_VERSION
  m.attr("__version__") = FUSEDMOSAIC_VERSION;
#endif
  fusedmosaic::bindings::BindGeometry(m);
  fusedmosaic::bindings::BindResiduals(m);
  fusedmosaic::bindings::BindProblem(m);
  fusedmosaic::bindings::BindSlidingWindow(m);
  fusedmosaic::bindings::BindRegistration(m);
  fusedmosaic::bindings::BindIo(m);
}
