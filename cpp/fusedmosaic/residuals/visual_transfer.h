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
#include <ceres/cost_function.h>
#include <ceres/jet.h>

#include <Eigen/Core>
#include <Eigen/Cholesky>
#include <Eigen/QR>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

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
  const Matrix3Xd& rays_m() const { return rays_m_; }
  double inv_sigma_v() const { return inv_sigma_v_; }

  // M = K H_l H_m^-1, the pixel transfer of normalised rays of frame m into frame l; false if
  // camera m's centre is on the plane.
  template <typename T>
  bool TransferMatrix(const T* const cam_l_from_world, const T* const cam_m_from_world,
                      const T* const plane, Matrix3<T>* M) const {
    using std::abs;
    const Matrix3<T> H_m = InducedHomography(cam_m_from_world, plane);
    const T det_m = H_m.determinant();
    if (!(abs(det_m) > T(1e-12))) return false;  // camera m centre on the plane
    *M = camera_matrix_.cast<T>() * InducedHomography(cam_l_from_world, plane) * H_m.inverse();
    return true;
  }

  // Point i transferred by M: its place (u, v) in frame l, pixels, the homogeneous depth q_z
  // and the whitened residual r = ((u, v) - p_l) / sigma_v; false if it goes to infinity. The
  // one arithmetic of every form of this residual (autodiff, analytic, condensed), so their
  // values agree bit for bit in doubles.
  template <typename T>
  bool TransferPoint(const Matrix3<T>& M, int i, T* u, T* v, T* q_z, T* r0, T* r1) const {
    using std::abs;
    const double* ray = rays_m_.col(i).data();  // Jet * double products only: rays are constants
    T q[3];
    for (int j = 0; j < 3; ++j) q[j] = M(j, 0) * ray[0] + M(j, 1) * ray[1] + M(j, 2) * ray[2];
    if (!(abs(q[2]) > T(1e-12))) return false;  // transferred to infinity
    *u = q[0] / q[2];
    *v = q[1] / q[2];
    *q_z = q[2];
    *r0 = (*u - points_l_(0, i)) * inv_sigma_v_;
    *r1 = (*v - points_l_(1, i)) * inv_sigma_v_;
    return true;
  }

  // The per-point kernel on a point's residual (r0, r1) and on its derivative rows (J0, J1):
  //     r' = w(s) r,   dr'/dtheta = w dr/dtheta + r w'(s) 2 r^T dr/dtheta,   s = |r|^2.
  template <typename Row>
  void ApplyKernel(double* r0, double* r1, Row* J0, Row* J1) const {
    if (loss_ == RobustLoss::kNone) return;
    const ceres::Jet<double, 1> w = RobustResidualScale(
        loss_, loss_scale_, ceres::Jet<double, 1>(*r0 * *r0 + *r1 * *r1, 0));
    const Row ds = 2.0 * (*r0 * *J0 + *r1 * *J1);
    *J0 = w.a * *J0 + (*r0 * w.v[0]) * ds;
    *J1 = w.a * *J1 + (*r1 * w.v[0]) * ds;
    *r0 *= w.a;
    *r1 *= w.a;
  }

  // cam_l_from_world, cam_m_from_world: [0..2] angle-axis, [3..5] translation (mm).
  // plane: pi = n / d (1/mm). residuals: 2N values, (x, y) per point.
  template <typename T>
  bool operator()(const T* const cam_l_from_world, const T* const cam_m_from_world,
                  const T* const plane, T* residuals) const {
    Matrix3<T> M;
    if (!TransferMatrix(cam_l_from_world, cam_m_from_world, plane, &M)) return false;
    for (int i = 0; i < num_points(); ++i) {
      T u, v, q_z, r0, r1;
      if (!TransferPoint(M, i, &u, &v, &q_z, &r0, &r1)) return false;
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
  // (cam_l_from_world: 6, cam_m_from_world: 6, plane: 3), with the analytic Jacobians of
  // VisualTransferCostFunction below. Use loss = kNone and a ceres::LossFunction for Ceres-side
  // robustness.
  static ceres::CostFunction* Create(const Eigen::Matrix3d& camera_matrix,
                                     const Matrix2Xd& points_l, const Matrix2Xd& points_m,
                                     double sigma_v, RobustLoss loss = RobustLoss::kNone,
                                     double loss_scale = 1.0);

  // The same block differentiated by ceres::AutoDiffCostFunction (the reference the analytic
  // Jacobians are tested against; a single point uses the fixed-size instantiation).
  static ceres::CostFunction* CreateAutoDiff(const VisualTransferCostFunctor& transfer) {
    auto* functor = new VisualTransferCostFunctor(transfer);
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

// VisualTransferCostFunctor's residuals with analytic Jacobians, for the solvers. Per block,
// M = K H_l H_m^-1 and its derivatives dM/dtheta with respect to the P free parameters are formed
// once with Jets (3x3 matrices); per point, with q = M ray, u = q_x / q_z, v = q_y / q_z,
//     dr/dtheta = [dq_x - u dq_z; dq_y - v dq_z] / (q_z sigma_v),   dq = (dM/dtheta) ray,
// and with a per-point kernel r' = w(s) r (s = |r|^2, w = sqrt(rho(s) / s), see above)
//     dr'/dtheta = w dr/dtheta + r w'(s) 2 r^T dr/dtheta.
// Automatic differentiation carried P-wide Jets through every point's transfer: in a SYN window
// step (13k residuals, replayed on the 2-core Xeon) one Jacobian evaluation took 0.64 ms with
// it, 0.52 ms with this. The residual values are VisualTransferCostFunctor's in doubles,
// bit for bit those of the residual-only evaluations (AutoDiffCostFunction's differ from them in
// the last bits: Jet division multiplies by the reciprocal).
//
// Condensed form (condense = true, for per-pair blocks with 2N > P + 1 residuals). Only through
// J^T J, J^T r and |r|^2 do a block's residuals enter a Gauss-Newton / Levenberg-Marquardt
// step, so the block can hand Ceres P + 1 residuals instead of 2N: with J = Q R (Householder),
//     r~ = [ (Q^T r)_1..P ; |(Q^T r)_P+1..2N| ],   J~ = [ R ; 0 ],
// J~^T J~ = J^T J, J~^T r~ = J^T r and |r~|^2 = |r|^2, so cost, gradient, normal equations,
// Jacobi scaling and model cost change are those of the 2N residuals (to rounding), and with
// them every step. The last row's true derivative is left out, as Gauss-Newton leaves out the
// change of r's component outside the range of J. Evaluated without Jacobians, the block returns
// [0, ..., 0, |r|] (the same cost; the minimizer only needs the cost there). In a SYN window
// step the ~13k residuals of ~66 pair blocks become ~400 and Ceres' per-residual work (validity
// checks, J^T J, column scaling) shrinks with them: the step's median 5.8 -> 3.7 ms, its linear
// solves 1.3 -> 0.15 ms (replay of 400 frames' window calls, 2-core Xeon; the same poses to
// 1e-13). The blocks with a free camera condense through their homography (below).
//
// Parameter blocks, in order: cam_l_from_world (6) if kFreeL, cam_m_from_world (6) if kFreeM,
// plane (3). A camera that is not free is a constant of the block (a camera held fixed in a
// sliding-window step: the derivatives then span only the free parameters).
template <bool kFreeL, bool kFreeM>
class VisualTransferCostFunction final : public ceres::CostFunction {
 public:
  static constexpr int kNumFree =
      (kFreeL ? kPoseSize : 0) + (kFreeM ? kPoseSize : 0) + kPlaneSize;

  // fixed_l / fixed_m: the constant pose of a camera that is not free (ignored otherwise).
  // condense: the condensed form above, if it has fewer residuals (2N > P + 1).
  VisualTransferCostFunction(VisualTransferCostFunctor transfer, const double* fixed_l,
                             const double* fixed_m, bool condense = false)
      : transfer_(std::move(transfer)),
        num_full_(2 * transfer_.num_points()),
        condensed_(condense && num_full_ > kNumFree + 1) {
    set_num_residuals(condensed_ ? kNumFree + 1 : num_full_);
    if (kFreeL) mutable_parameter_block_sizes()->push_back(kPoseSize);
    if (kFreeM) mutable_parameter_block_sizes()->push_back(kPoseSize);
    mutable_parameter_block_sizes()->push_back(kPlaneSize);
    for (int i = 0; i < kPoseSize; ++i) {
      fixed_l_[i] = kFreeL ? 0.0 : fixed_l[i];
      fixed_m_[i] = kFreeM ? 0.0 : fixed_m[i];
    }
  }

  bool condensed() const { return condensed_; }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    int b = 0;
    const double* cam_l = kFreeL ? parameters[b++] : fixed_l_;
    const double* cam_m = kFreeM ? parameters[b++] : fixed_m_;
    const double* plane = parameters[b];
    bool any_jacobian = false;
    for (int i = 0; jacobians != nullptr && i <= b; ++i) any_jacobian |= jacobians[i] != nullptr;
    if (!any_jacobian && !condensed_) return transfer_(cam_l, cam_m, plane, residuals);
    Eigen::VectorXd r(num_full_);
    if (!any_jacobian) {
      if (!transfer_(cam_l, cam_m, plane, r.data())) return false;
      Eigen::Map<Eigen::VectorXd>(residuals, kNumFree + 1).setZero();
      residuals[kNumFree] = r.norm();
      return true;
    }
    if (kNumFree > kHomographyDof && condensed_) {
      FullJacobian R = FullJacobian::Zero(kNumFree + 1, kNumFree);
      if (CondenseThroughHomography(cam_l, cam_m, plane, residuals, &R)) {
        WriteBlocks(R, jacobians);
        return true;
      }
    }
    FullJacobian J(num_full_, kNumFree);
    if (!Linearize(cam_l, cam_m, plane, r.data(), &J)) return false;
    if (!condensed_) {
      Eigen::Map<Eigen::VectorXd>(residuals, num_full_) = r;
      WriteBlocks(J, jacobians);
      return true;
    }
    FullJacobian R = FullJacobian::Zero(kNumFree + 1, kNumFree);
    if (kNumFree == kPlaneSize && CondenseByCholesky(J, r, residuals, &R)) {
      WriteBlocks(R, jacobians);
      return true;
    }
    const Eigen::HouseholderQR<FullJacobian> qr(J);
    r.applyOnTheLeft(qr.householderQ().adjoint());  // Q^T r
    Eigen::Map<Eigen::VectorXd>(residuals, kNumFree) = r.head<kNumFree>();
    residuals[kNumFree] = r.tail(num_full_ - kNumFree).norm();
    R.template topRows<kNumFree>() =
        qr.matrixQR().template topRows<kNumFree>().template triangularView<Eigen::Upper>();
    WriteBlocks(R, jacobians);
    return true;
  }

 private:
  using Jet = ceres::Jet<double, kNumFree>;
  using Gradient = Eigen::Matrix<double, 1, kNumFree>;
  using FullJacobian = Eigen::Matrix<double, Eigen::Dynamic, kNumFree>;
  static constexpr int kHomographyDof = 8;

  // The condensed form from the normal equations, R = chol(J^T J), r~ = R^-T J^T r: for the
  // pairs of two fixed cameras (P = 3, pi alone) whose J has full rank; ~5x cheaper than the
  // Householder QR at these sizes. False (QR then) if J^T J is not numerically positive definite.
  static bool CondenseByCholesky(const FullJacobian& J, const Eigen::VectorXd& r,
                                 double* residuals, FullJacobian* R) {
    const Eigen::Matrix<double, kNumFree, kNumFree> A = J.transpose() * J;
    const Eigen::LLT<Eigen::Matrix<double, kNumFree, kNumFree>> llt(A);
    if (llt.info() != Eigen::Success) return false;
    const Eigen::Matrix<double, kNumFree, kNumFree> U = llt.matrixU();
    if (!(U.diagonal().minCoeff() > 1e-6 * U.diagonal().maxCoeff())) return false;
    const Eigen::Matrix<double, kNumFree, 1> head =
        U.transpose().template triangularView<Eigen::Lower>().solve(J.transpose() * r);
    Eigen::Map<Eigen::Matrix<double, kNumFree, 1>> out(residuals);
    out = head;
    residuals[kNumFree] = std::sqrt(std::max(0.0, r.squaredNorm() - head.squaredNorm()));
    R->template topRows<kNumFree>() = U;
    return true;
  }

  // A pair sees its free parameters only through its transfer, the homography
  // h = M / M(2,2) (8 numbers), so J = G dh/dtheta with G = dr/dh (2N x 8): J^T J = (U dh)^T
  // (U dh) with U = chol(G^T G), and J^T r = (U dh)^T U^-T G^T r. For the blocks with a free
  // camera (P = 9 or 15, where J itself has rank <= 8) this gives the condensed form from an
  // 8 x 8 Cholesky of sums over the points, instead of the points' P-wide derivatives and a
  // (2N x P) QR: rows 0..7 = [U^-T G^T r; U dh], the last = the remainder, rows between zero.
  // G^T G is Jacobi-scaled before the factorisation (h mixes pixels and 1/pixels). False (the
  // QR then) if M(2,2) ~ 0 or G^T G is not numerically positive definite (< 4 points in
  // general position).
  bool CondenseThroughHomography(const double* cam_l, const double* cam_m, const double* plane,
                                 double* residuals, FullJacobian* R) const {
    using std::abs;
    using Vector8d = Eigen::Matrix<double, kHomographyDof, 1>;
    using Matrix8d = Eigen::Matrix<double, kHomographyDof, kHomographyDof>;
    Eigen::Matrix3d M;
    Matrix3<Jet> Mj;
    if (!Transfer(cam_l, cam_m, plane, &M, &Mj)) return false;
    if (!(abs(M(2, 2)) > 1e-6 * M.norm())) return false;
    Eigen::Matrix<double, kHomographyDof, kNumFree> dh;  // rows: h00 h01 h02 h10 h11 h12 h20 h21
    for (int e = 0; e < kHomographyDof; ++e) dh.row(e) = (Mj(e / 3, e % 3) / Mj(2, 2)).v;
    Matrix8d A = Matrix8d::Zero();
    Vector8d b = Vector8d::Zero();
    double rr = 0.0;
    for (int i = 0; i < transfer_.num_points(); ++i) {
      double u, v, q_z, r0, r1;
      if (!transfer_.TransferPoint(M, i, &u, &v, &q_z, &r0, &r1)) return false;
      const double* ray = transfer_.rays_m().col(i).data();
      // d(q_x / q_z) / dh_0k = ray_k / (h ray)_z, and so on
      const double g = transfer_.inv_sigma_v() * M(2, 2) / q_z;
      Vector8d g0, g1;
      g0 << g * ray[0], g * ray[1], g * ray[2], 0, 0, 0, -g * u * ray[0], -g * u * ray[1];
      g1 << 0, 0, 0, g * ray[0], g * ray[1], g * ray[2], -g * v * ray[0], -g * v * ray[1];
      transfer_.ApplyKernel(&r0, &r1, &g0, &g1);
      A.template selfadjointView<Eigen::Lower>().rankUpdate(g0);
      A.template selfadjointView<Eigen::Lower>().rankUpdate(g1);
      b += r0 * g0 + r1 * g1;
      rr += r0 * r0 + r1 * r1;
    }
    const Vector8d diagonal = A.diagonal();
    if (!(diagonal.minCoeff() > 0.0)) return false;
    const Vector8d scale = diagonal.cwiseSqrt().cwiseInverse();
    const Matrix8d scaled = scale.asDiagonal() *
                            Matrix8d(A.template selfadjointView<Eigen::Lower>()) *
                            scale.asDiagonal();
    const Eigen::LLT<Matrix8d> llt(scaled);
    if (llt.info() != Eigen::Success) return false;
    const Matrix8d Us = llt.matrixU();
    if (!(Us.diagonal().minCoeff() > 1e-7 * Us.diagonal().maxCoeff())) return false;
    const Matrix8d U = Us * scale.cwiseInverse().asDiagonal();  // U^T U = G^T G
    const Vector8d head = U.transpose().template triangularView<Eigen::Lower>().solve(b);
    Eigen::Map<Eigen::VectorXd> out(residuals, kNumFree + 1);
    out.setZero();
    out.template head<kHomographyDof>() = head;
    out[kNumFree] = std::sqrt(std::max(0.0, rr - head.squaredNorm()));
    R->template topRows<kHomographyDof>() = U * dh;
    return true;
  }

  // M from the functor's own double arithmetic (the residuals are then those of the
  // residual-only evaluations, bit for bit) and Mj, the same function in Jets seeded on the free
  // parameters (their derivatives dM/dtheta).
  bool Transfer(const double* cam_l, const double* cam_m, const double* plane,
                Eigen::Matrix3d* M, Matrix3<Jet>* Mj) const {
    Jet l[kPoseSize], m[kPoseSize], pi[kPlaneSize];
    int k = 0;
    for (int i = 0; i < kPoseSize; ++i) l[i] = kFreeL ? Jet(cam_l[i], k++) : Jet(cam_l[i]);
    for (int i = 0; i < kPoseSize; ++i) m[i] = kFreeM ? Jet(cam_m[i], k++) : Jet(cam_m[i]);
    for (int i = 0; i < kPlaneSize; ++i) pi[i] = Jet(plane[i], k++);
    return transfer_.TransferMatrix(cam_l, cam_m, plane, M) &&
           transfer_.TransferMatrix(l, m, pi, Mj);
  }

  // Columns of J to the requested parameter blocks (Ceres' row-major layout).
  void WriteBlocks(const FullJacobian& J, double** jacobians) const {
    int block = 0, column = 0;
    auto put = [&](int size) {
      if (jacobians[block] != nullptr) {
        Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
            jacobians[block], J.rows(), size) = J.middleCols(column, size);
      }
      ++block;
      column += size;
    };
    if (kFreeL) put(kPoseSize);
    if (kFreeM) put(kPoseSize);
    put(kPlaneSize);
  }

  // The 2N residuals and their (2N, P) Jacobian.
  bool Linearize(const double* cam_l, const double* cam_m, const double* plane,
                 double* residuals, FullJacobian* jacobian) const {
    Eigen::Matrix3d M;
    Matrix3<Jet> Mj;
    if (!Transfer(cam_l, cam_m, plane, &M, &Mj)) return false;
    Eigen::Matrix<double, 3, kNumFree> dM[3];  // dM[c].row(j) = d M(j, c) / d theta
    for (int j = 0; j < 3; ++j) {
      for (int c = 0; c < 3; ++c) dM[c].row(j) = Mj(j, c).v.transpose();
    }
    for (int i = 0; i < transfer_.num_points(); ++i) {
      double u, v, q_z, r0, r1;
      if (!transfer_.TransferPoint(M, i, &u, &v, &q_z, &r0, &r1)) return false;
      const double* ray = transfer_.rays_m().col(i).data();
      const Eigen::Matrix<double, 3, kNumFree> dq = dM[0] * ray[0] + dM[1] * ray[1] + dM[2] * ray[2];
      const double g = transfer_.inv_sigma_v() / q_z;
      Gradient J0 = (dq.row(0) - u * dq.row(2)) * g;
      Gradient J1 = (dq.row(1) - v * dq.row(2)) * g;
      transfer_.ApplyKernel(&r0, &r1, &J0, &J1);
      residuals[2 * i] = r0;
      residuals[2 * i + 1] = r1;
      jacobian->row(2 * i) = J0;
      jacobian->row(2 * i + 1) = J1;
    }
    return true;
  }

  VisualTransferCostFunctor transfer_;
  int num_full_;    // 2N
  bool condensed_;  // P + 1 residuals instead of 2N
  double fixed_l_[kPoseSize], fixed_m_[kPoseSize];
};

// The block of one pair's correspondences with analytic Jacobians; a camera whose pose is given
// here (fixed_l / fixed_m non-null) is a constant of the block, not a parameter block.
// condense: VisualTransferCostFunction's condensed form where it has fewer residuals.
// (Defined in visual_transfer.cc, where the four instantiations are compiled once.)
ceres::CostFunction* CreateVisualTransferCost(VisualTransferCostFunctor transfer,
                                              const double* fixed_l = nullptr,
                                              const double* fixed_m = nullptr,
                                              bool condense = false);

}  // namespace fusedmosaic
