// Per-domain binding entry points, called from module.cc.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <Eigen/Core>
#include <cmath>
#include <stdexcept>
#include <string>

namespace fusedmosaic::bindings {

void BindGeometry(pybind11::module_& m);
void BindResiduals(pybind11::module_& m);
void BindProblem(pybind11::module_& m);
void BindSlidingWindow(pybind11::module_& m);
void BindRegistration(pybind11::module_& m);
void BindIo(pybind11::module_& m);

using RowMatrixXd = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Array arguments are taken as numpy arrays and checked here, not as Eigen::Ref: a mismatched
// shape then gives a ValueError naming the argument and the shape got, where an Eigen::Ref that
// cannot bind gave pybind11's "incompatible function arguments" dump (and a 1-D array reached
// a matrix check as (N, 1)). c_style | forcecast: ints, lists, strided or big-endian input are
// converted (copied) to contiguous float64 first.
using DoubleArray =
    pybind11::array_t<double, pybind11::array::c_style | pybind11::array::forcecast>;

// "(2,)", "(2, 3)": the shape as numpy prints it.
inline std::string ShapeString(const pybind11::array& a) {
  std::string out = "(";
  for (pybind11::ssize_t i = 0; i < a.ndim(); ++i) {
    out += (i ? ", " : "") + std::to_string(a.shape(i));
  }
  return out + (a.ndim() == 1 ? ",)" : ")");
}

// Checks `size` finite values: shape (size,), or a (size, 1) column or (1, size) row (one row of
// an (N, size) table, which was accepted as a column before); any other shape is refused. The
// map points into `a`, which must outlive it.
inline Eigen::Map<const Eigen::VectorXd> ToVector(const DoubleArray& a, Eigen::Index size,
                                                  const char* name) {
  const bool vector_shape =
      a.ndim() == 1 || (a.ndim() == 2 && (a.shape(0) == 1 || a.shape(1) == 1));
  if (!vector_shape || a.size() != size) {
    throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(size) +
                                " values, got " +
                                (a.ndim() == 1 ? std::to_string(a.size())
                                               : "shape " + ShapeString(a)));
  }
  Eigen::Map<const Eigen::VectorXd> v(a.data(), size);
  if (!v.allFinite()) {
    throw std::invalid_argument(std::string(name) + ": contains NaN or infinite values");
  }
  return v;
}

// Checks a finite (rows, cols) matrix; rows < 0: any number of rows. As ToVector, the map points
// into `a`.
inline Eigen::Map<const RowMatrixXd> ToMatrix(const DoubleArray& a, Eigen::Index rows,
                                              Eigen::Index cols, const char* name) {
  if (a.ndim() != 2 || (rows >= 0 && a.shape(0) != rows) || a.shape(1) != cols) {
    throw std::invalid_argument(std::string(name) + ": expected shape (" +
                                (rows >= 0 ? std::to_string(rows) : std::string("N")) + ", " +
                                std::to_string(cols) + "), got " + ShapeString(a));
  }
  Eigen::Map<const RowMatrixXd> m(a.data(), a.shape(0), a.shape(1));
  if (!m.allFinite()) {
    throw std::invalid_argument(std::string(name) + ": contains NaN or infinite values");
  }
  return m;
}

inline Eigen::Matrix3d CheckCameraMatrix(const DoubleArray& K) {
  const Eigen::Matrix3d out = ToMatrix(K, 3, 3, "camera_matrix");
  if (std::abs(out.determinant()) < 1e-12) {
    throw std::invalid_argument("camera_matrix: matrix is singular");
  }
  return out;
}

// A plane pi = n / d: 3 finite values, non-zero. pi -> 0 is a plane ever farther away: pi = 0
// is the plane at infinity, which induces no homography of the plane's points.
inline Eigen::Vector3d ToPlane(const DoubleArray& plane, const char* name = "plane") {
  const Eigen::Vector3d pi = ToVector(plane, 3, name);
  if (!(pi.norm() > 1e-12)) {
    throw std::invalid_argument(std::string(name) +
                                ": pi = n/d must be non-zero (pi = 0 is the plane at infinity)");
  }
  return pi;
}

// BundleAdjuster and SlidingWindow take a mutex in every method, which a solve in another thread
// holds for its duration. Their bindings release the GIL before taking it (after converting the
// arguments, which needs the GIL): waiting for the mutex with the GIL held stopped every Python
// thread until the solve ended, not just the caller. Released() does so for a property getter.
template <typename Class, typename Return>
pybind11::cpp_function Released(Return (Class::*getter)() const) {
  return pybind11::cpp_function([getter](const Class& self) { return (self.*getter)(); },
                                pybind11::call_guard<pybind11::gil_scoped_release>());
}

}  // namespace fusedmosaic::bindings
