// Per-domain binding entry points, called from module.cc.
#pragma once

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

using RowMatrixXd = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// Shape / finiteness checks shared by the binding files; they throw std::invalid_argument,
// which pybind11 turns into ValueError.
inline void CheckSize(const Eigen::Ref<const Eigen::VectorXd>& v, Eigen::Index size,
                      const char* name) {
  if (v.size() != size) {
    throw std::invalid_argument(std::string(name) + ": expected " + std::to_string(size) +
                                " values, got " + std::to_string(v.size()));
  }
  if (!v.allFinite()) {
    throw std::invalid_argument(std::string(name) + ": contains NaN or infinite values");
  }
}

inline void CheckShape(const Eigen::Ref<const RowMatrixXd>& a, Eigen::Index rows, Eigen::Index cols,
                       const char* name) {
  if ((rows >= 0 && a.rows() != rows) || a.cols() != cols) {
    throw std::invalid_argument(std::string(name) + ": expected shape (" +
                                (rows >= 0 ? std::to_string(rows) : std::string("N")) + ", " +
                                std::to_string(cols) + "), got (" + std::to_string(a.rows()) +
                                ", " + std::to_string(a.cols()) + ")");
  }
  if (!a.allFinite()) {
    throw std::invalid_argument(std::string(name) + ": contains NaN or infinite values");
  }
}

inline Eigen::Matrix3d CheckCameraMatrix(const Eigen::Ref<const RowMatrixXd>& K) {
  CheckShape(K, 3, 3, "camera_matrix");
  Eigen::Matrix3d out = K;
  if (std::abs(out.determinant()) < 1e-12) {
    throw std::invalid_argument("camera_matrix: matrix is singular");
  }
  return out;
}

}  // namespace fusedmosaic::bindings
