// Constant-velocity motion prior (seed 000, Sec. 3.3.1 assumption 4, Eqs. 14-16 and 20).
//
// With poses as rigid transforms T_k (cam_from_world), the last pairwise motion is
// T_{k-1,k-2} = T_{k-1} T_{k-2}^-1 (cam_{k-1} from cam_{k-2}); repeating it once predicts
//     T_bar_k = T_{k-1,k-2} T_{k-1} = T_{k-1} T_{k-2}^-1 T_{k-1}              (Eq. 16)
//     mu_p(x_{k-1}, x_{k-2}) = [r(T_bar_k), t(T_bar_k)]                       (Eq. 15)
// and x_k | x_{k-1}, x_{k-2} ~ N(mu_p, Sigma_p), so
//     C_p = sum_{k>=3} (x_k - mu_p)^T Sigma_p^-1 (x_k - mu_p)                  (Eq. 20)
// The residual is r = S_p (x_k - mu_p), S_p = diag(1 / sigma_p). As in pose_prior.h, x_k - mu_p
// is the paper's difference of the angle-axis + translation 6-vectors with mu_p's rotation
// vector taken as the one nearest x_k's (PoseDifference, geometry/pose.h): mu_p comes out of
// ToPose with |r| <= pi, and near pi it and x_k could name nearly the same rotation by vectors
// 2 pi apart. The paper's plain difference bit for bit whenever their difference along mu_p's
// axis is below pi; d/dx_k = I.
//
// Standard deviations (appendix, Eq. 30): Sigma_p = diag(0.0044 x3, 15.2178 x3) is called a
// covariance there; for consistency with Sigma_EMT (whose values match the standard deviations
// of Sec. 4.1) we read it as standard deviations too: 0.0044 rad (0.25 deg) and 15.2 mm.
#pragma once

#include <ceres/autodiff_cost_function.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include <Eigen/Core>

#include "fusedmosaic/geometry/pose.h"
#include "fusedmosaic/residuals/pose_prior.h"
#include "fusedmosaic/util/format.h"

namespace fusedmosaic {

// sigma_p, [rad x3, mm x3] (appendix Eq. 30, read as standard deviations).
inline const Vector6d kDefaultMotionSigma =
    (Vector6d() << 0.0044, 0.0044, 0.0044, 15.2178, 15.2178, 15.2178).finished();

// Default motion gate (BundleAdjusterOptions::motion_gate_chi2): chi2(6)'s 0.999 quantile, the
// tracker gate's threshold (estimation/sequential.py gate_chi2).
inline constexpr double kDefaultMotionGateChi2 = 22.46;

// mu_p: the motion T_{k-1} T_{k-2}^-1 repeated `ratio` times from T_{k-1} (see below); ratio 1
// is Eq. 16 exactly (no round trip through the 6-vector).
template <typename T>
RigidTransform<T> PredictConstantVelocity(const RigidTransform<T>& T_km2,
                                          const RigidTransform<T>& T_km1, double ratio) {
  if (ratio == 1.0) return T_km1 * T_km2.Inverse() * T_km1;
  T motion[kPoseSize];
  (T_km1 * T_km2.Inverse()).ToPose(motion);
  for (int i = 0; i < kPoseSize; ++i) motion[i] *= T(ratio);
  return RigidTransform<T>::FromPose(motion) * T_km1;
}

struct ConstantVelocityCostFunctor {
  // ratio: (t_k - t_{k-1}) / (t_{k-1} - t_{k-2}) when frames are not evenly spaced (a dropped
  // frame, a live source falling behind): the last motion is repeated `ratio` times,
  // T_bar_k = (T_{k-1} T_{k-2}^-1)^ratio T_{k-1}, the power taken on the 6-vector of the motion
  // (its rotation exactly, its translation to first order in the rotation). 1: Eq. 16.
  explicit ConstantVelocityCostFunctor(const Vector6d& sigma, double ratio = 1.0)
      : sqrt_information_(SqrtInformationFromSigma(sigma)), ratio_(ratio) {}

  // Each pose: [0..2] angle-axis, [3..5] translation of cam_from_world, for frames k-2, k-1, k.
  // residuals: 6.
  template <typename T>
  bool operator()(const T* const cam_km2_from_world, const T* const cam_km1_from_world,
                  const T* const cam_k_from_world, T* residuals_ptr) const {
    T mu[kPoseSize];
    PredictConstantVelocity(RigidTransform<T>::FromPose(cam_km2_from_world),
                            RigidTransform<T>::FromPose(cam_km1_from_world), ratio_)
        .ToPose(mu);
    PoseDifference(cam_k_from_world, mu, residuals_ptr);  // x_k - mu_p, as in pose_prior.h
    Eigen::Map<Eigen::Matrix<T, 6, 1>> residuals(residuals_ptr);
    residuals.applyOnTheLeft(sqrt_information_.template cast<T>());
    return true;
  }

  static ceres::CostFunction* Create(const Vector6d& sigma = kDefaultMotionSigma,
                                     double ratio = 1.0) {
    return new ceres::AutoDiffCostFunction<ConstantVelocityCostFunctor, kPoseSize, kPoseSize,
                                           kPoseSize, kPoseSize>(
        new ConstantVelocityCostFunctor(sigma, ratio));
  }

 private:
  Matrix6d sqrt_information_;
  double ratio_;
};

// Checks the timing arguments of an add_frame: ratio finite and >= 0, sigma scale > 0. An
// infinite sigma scale releases the prior (no C_p term for the frame: the frame follows a gap
// too long for the velocity to carry over, estimation/motion.py motion_timing); ratio 0 then
// predicts the frame at the preceding camera (zero velocity), its starting pose when it has no
// tracker sample.
inline void CheckMotionTiming(double ratio, double sigma_scale, const char* what) {
  if (!(std::isfinite(ratio) && ratio >= 0 && !std::isnan(sigma_scale) && sigma_scale > 0)) {
    throw std::invalid_argument(std::string(what) +
                                ": motion_ratio must be finite and >= 0 and motion_sigma_scale "
                                "> 0 (inf: no motion prior), got " + FormatDouble(ratio) +
                                " and " + FormatDouble(sigma_scale));
  }
}

// Whether a frame's timing keeps its constant-velocity term (see CheckMotionTiming).
inline bool MotionPriorLinked(double sigma_scale) { return std::isfinite(sigma_scale); }

}  // namespace fusedmosaic
