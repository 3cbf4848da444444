// Visual transfer residual (seed 000, Sec. 3.3-3.4, Eqs. 13 and 18).
//
// A correspondence links a point p_m of frame m (image A) and a point p_l of frame l (image B),
// both in pixels. Through the plane pi, the point of frame m is predicted in frame l at
//     [mu; 1] ~ K H_l H_m^-1 K^-1 [p_m; 1],   H_k = R_k - t_k pi^T           (Eq. 13)
// and the residual is the whitened transfer error, in units of sigma_v:
//     r_i = (mu_i - p_l,i) / sigma_v,          C_v = sum_i |r_i|^2          (Eq. 18)
// (Ceres minimises 1/2 sum |r|^2; the factor 1/2 does not move the minimum.)
// The homography is built in normalised coordinates (geometry/homography.h); the rays
// K^-1 [p_m; 1] are precomputed and K is applied once per block, M = K H_l H_m^-1.
//
// Block layout. One functor holds the N correspondences of one image pair, so H_l H_m^-1 (two
// Rodrigues rotations and a 3x3 inverse, in Jets) is formed once per pair instead of once per
// point; with N = 1 the same functor is a per-point block. bench/bench_solvers.py measures both
// layouts; per-pair blocks are the default (problem/bundle_adjuster.h, BundleAdjusterOptions).
//
// Robust loss, applied per point. A ceres::LossFunction acts on a residual block's whole squared
// norm, which for a per-pair block would down-weight the entire pair, not the outlying points.
// So a per-pair block applies the loss itself, point by point: each point's residual is rescaled
//     r_i' = sqrt(rho(s_i) / s_i) r_i,   s_i = |r_i|^2,   hence |r_i'|^2 = rho(s_i),
// and the block's cost is exactly 1/2 sum_i rho(s_i), the per-point robust cost of Eq. 18 with a
// kernel. Its Jacobian is the exact (autodiff) derivative of r_i', so the solver minimises the
// honest robust objective; only the Gauss-Newton Hessian approximation differs from Ceres'
// Triggs correction. rho follows Ceres' conventions with scale a (in units of sigma_v):
//     Huber:  rho(s) = s for s <= a^2, 2 a sqrt(s) - a^2 otherwise
//     Cauchy: rho(s) = a^2 log(1 + s / a^2)
#pragma once

#include <ceres/autodiff_cost_function.h>
#include <ceres/jet.h>

#include <Eigen/Core>
#include <cmath>
#include <stdexcept>
#include <string>

#include "fusedmosaic/geometry/homography.h"
#include "fusedmosaic/geometry/plane.h"
#include "fusedmosaic/geometry/pose.h"

namespace fusedmosaic {

enum class RobustLoss { kNone, kHuber, kCauchy };

// "none" | "huber" | "cauchy" -> RobustLoss; throws std::invalid_argument otherwise.
inline RobustLoss RobustLossFromString(const std::string& name) {
  if (name == "none") return RobustLoss::kNone;
  if (name == "huber") return RobustLoss::kHuber;
  if (name == "cauchy") return RobustLoss::kCauchy;
  throw std::invalid_argument("loss: expected 'none', 'huber' or 'cauchy', got '" + name + "'");
}

// sqrt(rho(s) / s) for the kernels above, templated so Jets carry its derivative.
template <typename T>
T RobustResidualScale(RobustLoss loss, double scale, const T& s) {
  using std::log1p;
  using std::sqrt;
  const double b = scale * scale;
  switch (loss) {
    case RobustLoss::kNone:
      return T(1);
    case RobustLoss::kHuber:
      if (s <= T(b)) return T(1);
      return sqrt((T(2 * scale) * sqrt(s) - T(b)) / s);
    case RobustLoss::kCauchy: {
      const T x = s / T(b);
      // log1p(x) / x -> 1 - x/2 + x^2/3 near 0 (avoids 0/0 at an exact fit).
      if (x < T(1e-6)) return sqrt(T(1) - x / T(2) + x * x / T(3));
      return sqrt(log1p(x) / x);
    }
  }
  return T(1);
}

struct VisualTransferCostFunctor {
  using Matrix2Xd = Eigen::Matrix<double, 2, Eigen::Dynamic>;
  using Matrix3Xd = Eigen::Matrix<double, 3, Eigen::Dynamic>;

  // points_l, points_m: (2, N) pixels, column i is one correspondence (m -> l).
  // camera_matrix: K (invertible). sigma_v: pixels (paper Sec. 4.2: 1 px). loss_scale: pixels.
  VisualTransferCostFunctor(const Eigen::Matrix3d& camera_matrix, const Matrix2Xd& points_l,
                            const Matrix2Xd& points_m, double sigma_v, RobustLoss loss,
                            double loss_scale)
      : camera_matrix_(camera_matrix),
        points_l_(points_l),
        inv_sigma_v_(1.0 / sigma_v),
        loss_(loss),
        loss_scale_(loss_scale / sigma_v) {
    Matrix3Xd homogeneous(3, points_m.cols());
    homogeneous.topRows<2>() = points_m;
    homogeneous.row(2).setOnes();
    rays_m_ = camera_matrix.inverse() * homogeneous;
  }

  int num_points() const { return static_cast<int>(points_l_.cols()); }

  // cam_l_from_world, cam_m_from_world: [0..2] angle-axis, [3..5] translation (mm).
  // plane: pi = n / d (1/mm). residuals: 2N values, (x, y) per point.
  template <typename T>
  bool operator()(const T* const cam_l_from_world, const T* const cam_m_from_world,
                  const T* const plane, T* residuals) const {
    using std::abs;
    const Matrix3<T> H_m = InducedHomography(cam_m_from_world, plane);
    const T det_m = H_m.determinant();
    if (!(abs(det_m) > T(1e-12))) return false;  // camera m centre on the plane
    const Matrix3<T> M =
        camera_matrix_.cast<T>() * InducedHomography(cam_l_from_world, plane) * H_m.inverse();
    for (int i = 0; i < num_points(); ++i) {
      // Jet * double products only: the rays are constants.
      const double* ray = rays_m_.col(i).data();
      T q[3];
      for (int j = 0; j < 3; ++j) q[j] = M(j, 0) * ray[0] + M(j, 1) * ray[1] + M(j, 2) * ray[2];
      if (!(abs(q[2]) > T(1e-12))) return false;  // transferred to infinity
      T r0 = (q[0] / q[2] - points_l_(0, i)) * inv_sigma_v_;
      T r1 = (q[1] / q[2] - points_l_(1, i)) * inv_sigma_v_;
      if (loss_ != RobustLoss::kNone) {
        const T scale = RobustResidualScale(loss_, loss_scale_, T(r0 * r0 + r1 * r1));
        r0 *= scale;
        r1 *= scale;
      }
      residuals[2 * i] = r0;
      residuals[2 * i + 1] = r1;
    }
    return true;
  }

  // One block for all columns of points_l / points_m (N >= 1): 2N residuals, parameter blocks
  // (cam_l_from_world: 6, cam_m_from_world: 6, plane: 3). A single point uses the fixed-size
  // instantiation. Use loss = kNone and a ceres::LossFunction for Ceres-side robustness.
  static ceres::CostFunction* Create(const Eigen::Matrix3d& camera_matrix,
                                     const Matrix2Xd& points_l, const Matrix2Xd& points_m,
                                     double sigma_v, RobustLoss loss = RobustLoss::kNone,
                                     double loss_scale = 1.0) {
    auto* functor =
        new VisualTransferCostFunctor(camera_matrix, points_l, points_m, sigma_v, loss, loss_scale);
    if (functor->num_points() == 1) {
      return new ceres::AutoDiffCostFunction<VisualTransferCostFunctor, 2, kPoseSize, kPoseSize,
                                             kPlaneSize>(functor);
    }
    return new ceres::AutoDiffCostFunction<VisualTransferCostFunctor, ceres::DYNAMIC, kPoseSize,
                                           kPoseSize, kPlaneSize>(functor,
                                                                  2 * functor->num_points());
  }

 private:
  Eigen::Matrix3d camera_matrix_;
  Matrix3Xd rays_m_;  // K^-1 [p_m; 1], normalised coordinates of frame m
  Matrix2Xd points_l_;
  double inv_sigma_v_;
  RobustLoss loss_;
  double loss_scale_;  // in units of sigma_v
};

}  // namespace fusedmosaic
