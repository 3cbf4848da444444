// Python bindings of cpp/fusedmosaic/residuals: evaluation helpers that return each functor's
// residuals and Jacobians, so tests can check them against numeric derivatives.
#include <pybind11/eigen.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "bindings/bind.h"
#include "fusedmosaic/residuals/constant_velocity.h"
#include "fusedmosaic/residuals/pose_prior.h"
#include "fusedmosaic/residuals/visual_transfer.h"
#include "fusedmosaic/util/format.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

// Evaluates cost at the given parameter blocks; returns (residuals, (jacobian per block, ...)),
// each Jacobian (num_residuals, block_size), row-major as Ceres lays it out.
py::tuple Evaluate(const ceres::CostFunction& cost, const std::vector<const double*>& params,
                   bool with_jacobians = true) {
  const int n = cost.num_residuals();
  const std::vector<int32_t>& sizes = cost.parameter_block_sizes();
  Eigen::VectorXd residuals(n);
  std::vector<RowMatrixXd> jacobians;
  std::vector<double*> jacobian_ptrs;
  jacobians.reserve(sizes.size());
  for (int32_t size : sizes) {
    jacobians.emplace_back(n, size);
    jacobian_ptrs.push_back(jacobians.back().data());
  }
  if (!cost.Evaluate(params.data(), residuals.data(),
                     with_jacobians ? jacobian_ptrs.data() : nullptr)) {
    throw std::invalid_argument(
        "evaluation failed: degenerate geometry (a camera centre on the plane, or a point "
        "transferred to infinity)");
  }
  if (!with_jacobians) return py::make_tuple(residuals, py::tuple());
  py::tuple jac(jacobians.size());
  for (size_t i = 0; i < jacobians.size(); ++i) jac[i] = py::cast(jacobians[i]);
  return py::make_tuple(residuals, jac);
}

Vector6d CheckedPose(const DoubleArray& v, const char* name) {
  return ToVector(v, kPoseSize, name);
}

Vector6d CheckedSigma(const DoubleArray& a, const char* name) {
  const Vector6d v = ToVector(a, kPoseSize, name);
  for (int i = 0; i < kPoseSize; ++i) {
    if (!(v[i] > 0)) {
      throw std::invalid_argument(std::string(name) + "[" + std::to_string(i) +
                                  "]: standard deviations must be > 0");
    }
  }
  return v;
}

}  // namespace

void BindResiduals(py::module_& m) {
  m.attr("DEFAULT_EMT_SIGMA") = Eigen::VectorXd(kDefaultEmtSigma);
  m.attr("DEFAULT_MOTION_SIGMA") = Eigen::VectorXd(kDefaultMotionSigma);

  m.def(
      "evaluate_visual_transfer",
      [](const DoubleArray& cam_l_from_world, const DoubleArray& cam_m_from_world,
         const DoubleArray& plane, const DoubleArray& points_l_array,
         const DoubleArray& points_m_array, const DoubleArray& camera_matrix,
         double sigma_v_px, const std::string& loss, double loss_scale_px,
         const std::string& jacobians, const std::string& fixed_cameras, bool condense) {
        const Vector6d pose_l = CheckedPose(cam_l_from_world, "cam_l_from_world");
        const Vector6d pose_m = CheckedPose(cam_m_from_world, "cam_m_from_world");
        // As everywhere else (set_plane, the geometry functions): pi = 0 was evaluated to
        // residuals of 0 (points at infinity), sigma_v_px = inf too.
        const Eigen::Vector3d pi = ToPlane(plane);
        const auto points_l = ToMatrix(points_l_array, -1, 2, "points_l");
        const auto points_m = ToMatrix(points_m_array, points_l.rows(), 2, "points_m");
        if (points_l.rows() < 1) throw std::invalid_argument("points_l: needs at least 1 row");
        if (!(std::isfinite(sigma_v_px) && sigma_v_px > 0)) {
          throw std::invalid_argument("sigma_v_px: must be > 0 and finite, got " +
                                      FormatDouble(sigma_v_px));
        }
        if (!(std::isfinite(loss_scale_px) && loss_scale_px > 0)) {
          throw std::invalid_argument("loss_scale_px: must be > 0 and finite, got " +
                                      FormatDouble(loss_scale_px));
        }
        const Eigen::Matrix3d K = CheckCameraMatrix(camera_matrix);
        if (jacobians != "analytic" && jacobians != "autodiff" && jacobians != "none") {
          throw std::invalid_argument(
              "jacobians: expected 'analytic', 'autodiff' or 'none', got '" + jacobians + "'");
        }
        if (fixed_cameras != "none" && fixed_cameras != "l" && fixed_cameras != "m" &&
            fixed_cameras != "both") {
          throw std::invalid_argument(
              "fixed_cameras: expected 'none', 'l', 'm' or 'both', got '" + fixed_cameras + "'");
        }
        const bool fixed_l = fixed_cameras == "l" || fixed_cameras == "both";
        const bool fixed_m = fixed_cameras == "m" || fixed_cameras == "both";
        if (jacobians == "autodiff" && (fixed_l || fixed_m || condense)) {
          throw std::invalid_argument(
              "jacobians='autodiff' is the reference block: both cameras free, not condensed");
        }
        const VisualTransferCostFunctor transfer(K, points_l.transpose(), points_m.transpose(),
                                                 sigma_v_px, RobustLossFromString(loss),
                                                 loss_scale_px);
        std::unique_ptr<ceres::CostFunction> cost(
            jacobians == "autodiff"
                ? VisualTransferCostFunctor::CreateAutoDiff(transfer)
                : CreateVisualTransferCost(transfer, fixed_l ? pose_l.data() : nullptr,
                                           fixed_m ? pose_m.data() : nullptr, condense));
        std::vector<const double*> params;
        if (!fixed_l) params.push_back(pose_l.data());
        if (!fixed_m) params.push_back(pose_m.data());
        params.push_back(pi.data());
        return Evaluate(*cost, params, jacobians != "none");
      },
      "cam_l_from_world"_a, "cam_m_from_world"_a, "plane"_a, "points_l"_a, "points_m"_a,
      "camera_matrix"_a, "sigma_v_px"_a = 1.0, "loss"_a = "none", "loss_scale_px"_a = 2.0,
      "jacobians"_a = "analytic", "fixed_cameras"_a = "none", "condense"_a = false,
      "Visual transfer residual (Eq. 13, 18) of one pair block and its Jacobians.\n\n"
      "cam_l_from_world, cam_m_from_world : (6,) float64 [r, t]\nplane : (3,) float64\n"
      "points_l, points_m : (N, 2) float64 pixels (transfer m -> l)\n"
      "camera_matrix : (3, 3) float64\nloss : 'none' | 'huber' | 'cauchy' (per point)\n"
      "jacobians : 'analytic' (what the solvers use) | 'autodiff' (the reference) | 'none'\n"
      "fixed_cameras : 'none' | 'l' | 'm' | 'both': cameras that are constants of the block\n"
      "  (their Jacobians are not returned), as in a sliding-window step\n"
      "condense : the condensed form (P + 1 residuals with the same J^T J, J^T r and cost)\n"
      "Returns (residuals (2N,), (J_l (2N, 6), J_m (2N, 6), J_plane (2N, 3))); residuals are\n"
      "(mu - p_l) / sigma_v, interleaved x, y per point.");

  m.def(
      "evaluate_pose_prior",
      [](const DoubleArray& cam_from_world, const DoubleArray& measurement,
         const DoubleArray& sigma) {
        const Vector6d x = CheckedPose(cam_from_world, "cam_from_world");
        std::unique_ptr<ceres::CostFunction> cost(PosePriorCostFunctor::Create(
            CheckedPose(measurement, "measurement"), CheckedSigma(sigma, "sigma")));
        return Evaluate(*cost, {x.data()});
      },
      "cam_from_world"_a, "measurement"_a, "sigma"_a = Eigen::VectorXd(kDefaultEmtSigma),
      "EMT pose prior residual (Eq. 19) S (x - z), S = diag(1 / sigma), and its Jacobian.\n\n"
      "cam_from_world, measurement : (6,) float64 [r, t]\n"
      "sigma : (6,) float64 standard deviations (default: appendix Eq. 30)\n"
      "Returns (residuals (6,), (J (6, 6),)).");

  m.def(
      "evaluate_constant_velocity",
      [](const DoubleArray& cam_km2_from_world, const DoubleArray& cam_km1_from_world,
         const DoubleArray& cam_k_from_world, const DoubleArray& sigma, double ratio) {
        const Vector6d x2 = CheckedPose(cam_km2_from_world, "cam_km2_from_world");
        const Vector6d x1 = CheckedPose(cam_km1_from_world, "cam_km1_from_world");
        const Vector6d x0 = CheckedPose(cam_k_from_world, "cam_k_from_world");
        CheckMotionTiming(ratio, 1.0, "evaluate_constant_velocity");
        std::unique_ptr<ceres::CostFunction> cost(
            ConstantVelocityCostFunctor::Create(CheckedSigma(sigma, "sigma"), ratio));
        return Evaluate(*cost, {x2.data(), x1.data(), x0.data()});
      },
      "cam_km2_from_world"_a, "cam_km1_from_world"_a, "cam_k_from_world"_a,
      "sigma"_a = Eigen::VectorXd(kDefaultMotionSigma), "ratio"_a = 1.0,
      "Constant-velocity prior residual (Eq. 15, 16, 20) S_p (x_k - mu_p), "
      "mu_p = T_{k-1} T_{k-2}^-1 T_{k-1}.\n\n"
      "cam_km2_from_world, cam_km1_from_world, cam_k_from_world : (6,) float64 poses of frames\n"
      "k-2, k-1, k\nsigma : (6,) float64 standard deviations (default: appendix Eq. 30)\n"
      "ratio : (t_k - t_k-1) / (t_k-1 - t_k-2); the last motion's 6-vector times ratio is\n"
      "    repeated (1: Eq. 16)\n"
      "Returns (residuals (6,), (J_km2 (6, 6), J_km1 (6, 6), J_k (6, 6))).");
}

}  // namespace fusedmosaic::bindings
