// Pose prior from an EM-tracker measurement (seed 000, Sec. 3.3.1 assumption 2, Eqs. 10 and 19).
//
// Each EMT measurement z_k = [r_z, t_z] is a Gaussian observation of the camera pose x_k with
// diagonal covariance Sigma_EMT:  z_k | x_k ~ N(x_k, Sigma_EMT), so
//     C_EMT = sum_k (z_k - x_k)^T Sigma_EMT^-1 (z_k - x_k)                     (Eq. 19)
// and the residual is r = S (x - z) with S = Sigma_EMT^-1/2 = diag(1 / sigma).
//
// x - z is the paper's difference of the 6-vectors, angle-axis minus angle-axis, with one
// change: z's angle-axis vector is the one of its rotation nearest x's (PoseDifference,
// geometry/pose.h). A rotation near pi has two vectors 2 pi apart (+pi u, -pi u), so the plain
// difference of an estimate and a measurement 0.02 rad apart was ~2 pi, and tracker noise that
// flipped the measured vector pulled the estimate hundreds of sigma away (review 52). Wherever
// the plain difference has a component along z's axis below pi, which covers every error of a
// working tracker, the residual is the paper's bit for bit and linear in x (d/dx = I). The
// geodesic log(R_x R_z^T) equals it to first order for small errors (SYN 152 frames, seeds 0
// and 1: e_M of lba-emt and ba-emt within 2e-8 px of this one) and would also undo the chart's
// stretch near |r| = pi (directions across the axis count up to pi / 2 times their geodesic
// angle), but it is not Eq. 19: we keep the paper's cost and mend only its wrap.
//
// Standard deviations (appendix, Eq. 30). The appendix lists Sigma_EMT = diag(0.017, 0.017,
// 0.017, 1, 1, 1) and calls it a covariance, but Sec. 4.1 states the tracker errors as 1 deg
// (= 0.017 rad) and 1 mm standard deviations; we read the diagonal as standard deviations.
#pragma once

#include <ceres/autodiff_cost_function.h>

#include <Eigen/Core>

#include "fusedmosaic/geometry/pose.h"

namespace fusedmosaic {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;

// sigma_EMT, [rad x3, mm x3] (appendix Eq. 30, read as standard deviations).
inline const Vector6d kDefaultEmtSigma =
    (Vector6d() << 0.017, 0.017, 0.017, 1.0, 1.0, 1.0).finished();

// Square-root information diag(1 / sigma) from diagonal standard deviations (all > 0).
inline Matrix6d SqrtInformationFromSigma(const Vector6d& sigma) {
  return sigma.cwiseInverse().asDiagonal();
}

struct PosePriorCostFunctor {
  // measurement: z = [r (rad), t (mm)] of cam_from_world; sigma: standard deviations (6).
  PosePriorCostFunctor(const Vector6d& measurement, const Vector6d& sigma)
      : measurement_(measurement), sqrt_information_(SqrtInformationFromSigma(sigma)) {}

  // cam_from_world: [0..2] angle-axis, [3..5] translation. residuals: 6.
  template <typename T>
  bool operator()(const T* const cam_from_world, T* residuals_ptr) const {
    T z[kPoseSize];
    for (int i = 0; i < kPoseSize; ++i) z[i] = T(measurement_[i]);
    PoseDifference(cam_from_world, z, residuals_ptr);  // x - z, z's rotation vector nearest x's
    Eigen::Map<Eigen::Matrix<T, 6, 1>> residuals(residuals_ptr);
    residuals.applyOnTheLeft(sqrt_information_.template cast<T>());
    return true;
  }

  static ceres::CostFunction* Create(const Vector6d& measurement,
                                     const Vector6d& sigma = kDefaultEmtSigma) {
    return new ceres::AutoDiffCostFunction<PosePriorCostFunctor, kPoseSize, kPoseSize>(
        new PosePriorCostFunctor(measurement, sigma));
  }

 private:
  Vector6d measurement_;
  Matrix6d sqrt_information_;
};

}  // namespace fusedmosaic
