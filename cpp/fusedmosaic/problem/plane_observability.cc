#include "fusedmosaic/problem/plane_observability.h"

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <ceres/cost_function.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include "fusedmosaic/geometry/pose.h"

namespace fusedmosaic {

// sqrt(trace(Cov_pi)) / plane_norm at the solution: the marginal covariance of the plane given
// every cost of the problem, Cov = (J^T J)^+ over the free parameters (residuals are whitened by
// their sigmas, so it is absolute). A direction of J^T J without information that moves pi makes
// pi unobservable (inf); one confined to the poses (a free camera without any cost) does not
// concern pi and is left out, as the pseudo-inverse does. Built from one Jacobian evaluation of
// each residual block (a window step's blocks, and a BundleAdjuster's with per-pair blocks and
// EMT priors, have no ceres::LossFunction and no manifolds, so these are the Jacobians Ceres
// uses), J_a^T J_b added block by block: ceres::Covariance (DENSE_SVD)
// took ~6 ms on a SYN step of 11k residuals, Problem::Evaluate into a CRSMatrix 1.5 ms (it
// builds a program and an evaluator per call), this ~0.6 ms, mostly the evaluation.
double PlaneRelativeStd(ceres::Problem* problem, double* plane,
                        const std::vector<double*>& free_poses, double plane_norm) {
  using RowMajorMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  std::map<const double*, int> column;  // first column of each free block; the plane's last
  int n = 0;
  for (const double* p : free_poses) {
    column[p] = n;
    n += kPoseSize;
  }
  column[plane] = n;
  n += kPlaneSize;
  Eigen::MatrixXd H = Eigen::MatrixXd::Zero(n, n);
  std::vector<ceres::ResidualBlockId> blocks;
  problem->GetResidualBlocks(&blocks);
  std::vector<double*> parameters;
  std::vector<RowMajorMatrix> jacobians;
  std::vector<double*> jacobian_ptrs;
  std::vector<int> cols;
  Eigen::VectorXd residuals;
  for (const ceres::ResidualBlockId block : blocks) {
    problem->GetParameterBlocksForResidualBlock(block, &parameters);
    const ceres::CostFunction* cost = problem->GetCostFunctionForResidualBlock(block);
    const int m = cost->num_residuals();
    const size_t k = parameters.size();
    jacobians.resize(k);
    jacobian_ptrs.assign(k, nullptr);
    cols.assign(k, -1);
    bool touches_free = false;
    for (size_t b = 0; b < k; ++b) {
      const auto it = column.find(parameters[b]);
      if (it == column.end()) continue;  // held constant in this step
      cols[b] = it->second;
      jacobians[b].resize(m, cost->parameter_block_sizes()[b]);
      jacobian_ptrs[b] = jacobians[b].data();
      touches_free = true;
    }
    if (!touches_free) continue;
    residuals.resize(m);
    if (!cost->Evaluate(parameters.data(), residuals.data(), jacobian_ptrs.data())) {
      return std::numeric_limits<double>::infinity();
    }
    for (size_t a = 0; a < k; ++a) {
      if (cols[a] < 0) continue;
      const RowMajorMatrix& Ja = jacobians[a];
      H.block(cols[a], cols[a], Ja.cols(), Ja.cols()).noalias() += Ja.transpose() * Ja;
      for (size_t b = a + 1; b < k; ++b) {
        if (cols[b] < 0) continue;
        const RowMajorMatrix& Jb = jacobians[b];
        const Eigen::MatrixXd ab = Ja.transpose() * Jb;
        H.block(cols[a], cols[b], ab.rows(), ab.cols()) += ab;
        H.block(cols[b], cols[a], ab.cols(), ab.rows()) += ab.transpose();
      }
    }
  }
  // Jacobi scaling, H = D S D with D = diag(H)^(1/2), so that the null test is relative to each
  // parameter's own information: unscaled, the rotations' (visual, ~1e11) set the tolerance,
  // and a start-up's camera translations, held by their tracker samples alone (~0.5), counted
  // as no information: pi was "unobservable" (inf) in start-ups with ~160 pairs and a tracker
  // gap, which then waited to startup_wait_frames. A parameter without information (a zero
  // diagonal) stays in S's null space. H^+ = D^-1 S^+ D^-1 where S is invertible.
  const Eigen::VectorXd diagonal = H.diagonal();
  Eigen::VectorXd inv_d = Eigen::VectorXd::Zero(n);
  for (int i = 0; i < n; ++i) {
    if (diagonal(i) > 0.0) inv_d(i) = 1.0 / std::sqrt(diagonal(i));
  }
  const Eigen::MatrixXd S = inv_d.asDiagonal() * H * inv_d.asDiagonal();
  const auto d_plane = inv_d.tail<kPlaneSize>();
  // Only pi's 3x3 block of S^-1 is needed. With pi ordered last, S = L L^T gives it as
  // (L_pp L_pp^T)^-1, L_pp the factor's last 3x3 block (the Schur complement of the poses):
  // a Cholesky factorisation, n^3 / 3 flops, where the eigen-decomposition with eigenvectors
  // took 1.2 s at 150 frames (n = 903; review). Taken when S is positive definite and so well
  // conditioned (Eigen's 1-norm rcond estimate above kMinRcond: lambda_min / lambda_max above
  // ~1e-8 / n, far above the eigen path's null tolerance of 1e-12) that every eigenvalue enters
  // the pseudo-inverse: both paths give one value. Otherwise (a parameter without information,
  // a near-null direction) the eigen path decides which null directions move pi.
  constexpr double kMinRcond = 1e-8;
  const Eigen::LLT<Eigen::MatrixXd> llt(S);
  if (llt.info() == Eigen::Success && llt.rcond() > kMinRcond) {
    const Eigen::Matrix3d L_pp =
        llt.matrixLLT().bottomRightCorner<kPlaneSize, kPlaneSize>().triangularView<Eigen::Lower>();
    const Eigen::Matrix3d cov = (L_pp * L_pp.transpose()).inverse();  // of the scaled pi
    double trace = 0.0;
    for (int i = 0; i < kPlaneSize; ++i) trace += cov(i, i) * d_plane(i) * d_plane(i);
    if (std::isfinite(trace)) return std::sqrt(trace) / plane_norm;
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(S);
  if (eig.info() != Eigen::Success) return std::numeric_limits<double>::infinity();
  const Eigen::VectorXd& lambda = eig.eigenvalues();  // ascending
  const double tolerance = 1e-12 * std::max(lambda(n - 1), 0.0);
  double trace = 0.0;
  for (int k = 0; k < n; ++k) {
    const auto v_plane = eig.eigenvectors().col(k).tail<kPlaneSize>();
    if (lambda(k) > tolerance) {
      trace += v_plane.cwiseProduct(d_plane).squaredNorm() / lambda(k);
    } else if (v_plane.norm() > 1e-6) {
      return std::numeric_limits<double>::infinity();  // (a zero-information pi included)
    }
  }
  return std::sqrt(trace) / plane_norm;
}

}  // namespace fusedmosaic
