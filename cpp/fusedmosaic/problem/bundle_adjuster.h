// Bundle adjustment over all frames: BAVis and BAVis+EMT (seed 000, Sec. 3.4, Eq. 17).
//
//     (X, pi) = argmin  C_v + C_EMT + C_p                                        (Eq. 17)
// with the visual transfer term C_v (residuals/visual_transfer.h, Eq. 18), the EM-tracker pose
// prior C_EMT (residuals/pose_prior.h, Eq. 19) and the constant-velocity prior C_p
// (residuals/constant_velocity.h, Eq. 20). Ceres reports costs as 1/2 of these sums.
//
// The adjuster owns the parameters: one pose [r, t] (cam_from_world) per frame id and the plane
// pi = n / d. Each Solve() builds a fresh ceres::Problem over the stored data, so frames, pairs
// and poses can be added or changed between solves. Every public method takes an internal mutex:
// a call made from another thread while Solve() runs waits for it to finish.
//
// Gauge. Without EMT priors (BAVis) every term is invariant to a change of world frame by a
// similarity: a rigid motion (poses T_k -> T_k A, the plane re-expressed accordingly) and a scale
// (t_k -> s t_k, pi -> pi / s leaves H_k = R_k - t_k pi^T unchanged). The frame -> reference
// homographies G_k = H_0 H_k^-1 are gauge-invariant, so any representative will do; we fix the
// 7 degrees of freedom so that the normal equations are not singular:
//   * rigid motion: the first frame (lowest id) in the problem is held constant, unless the user
//     already set a frame constant with SetConstantFrame;
//   * scale: the plane block lives on ceres::SphereManifold<3>, i.e. |pi| = 1 / (distance from
//     the world origin to the plane) keeps its initial value. Skipped when two or more frames are
//     constant, whose baseline already fixes the scale.
// The constant-velocity prior is only approximately gauge-invariant and does not change this.
// With EMT priors in the problem (use_emt and at least one measurement) no constraint is added.
// The priors fix the gauge only with at least two measured frames whose centres differ (their
// baseline sets the scale): one prior fixes its camera's 6 DoF but not the scale (the world
// scaled about that camera's centre leaves its pose and every transfer H_l H_m^-1 unchanged).
// With one measured frame the plane's distance then stays where it started (plane_relative_std
// inf), or, with C_p, is held only weakly by C_p (Levenberg-Marquardt crawled to its iteration
// limit; review 46). Disconnected groups of frames keep their own relative freedom.
#pragma once

#include <ceres/solver.h>

#include <Eigen/Core>
#include <array>
#include <map>
#include <limits>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "fusedmosaic/residuals/constant_velocity.h"
#include "fusedmosaic/residuals/pose_prior.h"
#include "fusedmosaic/residuals/visual_transfer.h"

namespace fusedmosaic {

struct BundleAdjusterOptions {
  double sigma_v_px = 1.0;                      // paper Sec. 4.2: sigma_v = 1 px
  Vector6d emt_sigma = kDefaultEmtSigma;        // appendix Eq. 30, standard deviations (rad, mm)
  Vector6d motion_sigma = kDefaultMotionSigma;  // appendix Eq. 30, standard deviations (rad, mm)
  std::string loss = "none";                    // "none" | "huber" | "cauchy", applied per point
  double loss_scale_px = 2.0;                   // robust kernel scale, pixels
  // "auto" or a Ceres linear solver name in lower case: "dense_schur", "sparse_schur",
  // "sparse_normal_cholesky", "dense_qr", "dense_normal_cholesky", "iterative_schur".
  std::string linear_solver = "auto";
  // "levenberg_marquardt" or "dogleg" (Ceres' trust region strategy). Levenberg-Marquardt damps
  // every step by mu diag(J^T J): along directions that only a few EMT priors constrain (a
  // start-up of 80 frames whose tracker came on at its last 2: moving the whole visual structure
  // onto the samples) it crawled, 110-210 iterations; Powell's dogleg takes the Gauss-Newton
  // step whenever it fits in the trust region: 7-58 (see SequentialOptions.startup_trust_region).
  std::string trust_region = "levenberg_marquardt";
  // "per_pair": one residual block per image pair (default, measured faster in
  // bench/bench_solvers.py); "per_point": one block per correspondence (robust loss via Ceres).
  std::string residual_blocks = "per_pair";
  // Per-pair blocks hand Ceres their condensed form (residuals/visual_transfer.h): P + 1
  // residuals with the pair's J^T J, J^T r and cost instead of 2N, so the same steps to
  // rounding with Ceres' per-residual work cut (~13k -> ~400 residuals in a SYN window step).
  // false: the 2N residuals.
  bool condense_pairs = true;
  int max_iterations = 100;
  double function_tolerance = 1e-10;
  double gradient_tolerance = 1e-10;
  double parameter_tolerance = 1e-8;
  int num_threads = 2;
  bool use_emt = true;           // add C_EMT for frames with a measurement
  bool use_motion_prior = true;  // add C_p for consecutive frame ids k-2, k-1, k
  // Motion gate (not in the paper; motion_gate.h): after a solve the C_p blocks whose whitened
  // squared norm is above this and the largest among their neighbours are released (left out
  // of this solve, as after a pause) and the problem solved again, in rounds, at most a quarter
  // of the blocks. The constant-velocity model cannot describe every motion (a scope spun in at
  // 30 deg per frame is 120 sigma_p of rotation): such a block pulled textured frames up to
  // 263 px off. Simulated solutions (SYN, hand-held, with black frames) peak at 1.1. inf: off.
  double motion_gate_chi2 = kDefaultMotionGateChi2;
  // Compute SolveSummary::plane_relative_std: a dense eigen-decomposition of the
  // (6 N + 3)^2 information matrix, for small problems (the sequential start-up).
  bool plane_std = false;
  // With plane_std, only the poses of frames in a pair enter the covariance; the others (with
  // their EMT and motion priors only) are held at their values, i.e. conditioned on, so the
  // std is a lower bound. Dense in 6 M + 3 for M paired frames: a long ba-emt run with few
  // registered pairs.
  bool plane_std_paired_only = false;

  // Throws std::invalid_argument naming the offending field.
  void Validate() const;
};

// Ceres options for one solve under `options`: its stopping criteria and threads, silent.
ceres::Solver::Options SolverOptionsFor(const BundleAdjusterOptions& options,
                                        ceres::LinearSolverType linear_solver);

// The iterations of a solve: Ceres' summary lists iteration 0 (the evaluation at the start) in
// `iterations` and counts it as a successful step, so both counts exceeded max_num_iterations
// by one. Both summaries report this count, summed over a step's or solve's Ceres runs.
int CeresIterations(const ceres::Solver::Summary& summary);
// A cost of Ceres' summary, NaN where Ceres left its -1 "not computed" (a solve that failed to
// evaluate its residuals): costs are >= 0, and -1 read as a perfect fit.
double CeresCost(double cost);

struct SolveSummary {
  int iterations = 0;  // Ceres iterations (CeresIterations), at most max_iterations per round
  double initial_cost = 0.0;  // NaN when the solve could not evaluate it (FAILURE)
  double final_cost = 0.0;
  // Per-term costs at the solution (Ceres convention: 1/2 sum of squared whitened residuals,
  // robust-kernel values for the visual term when a loss is set); NaN for a term that cannot be
  // evaluated there (a camera centre on the plane).
  double visual_cost = 0.0;
  double emt_cost = 0.0;
  double motion_cost = 0.0;
  double solve_time_s = 0.0;  // Ceres' total time (preprocessing + minimisation)
  std::string termination;    // "CONVERGENCE", "NO_CONVERGENCE", "FAILURE", ...
  std::string message;        // Ceres' explanation of the termination
  std::string full_report;    // Ceres' FullReport(): timings per stage, problem sizes
  std::string linear_solver;  // the linear solver used, lower case
  int num_residual_blocks = 0;
  int num_residuals = 0;
  int num_parameters = 0;       // all parameters in the problem (constant ones included)
  int num_free_parameters = 0;  // optimised tangent-space parameters
  int num_visual_blocks = 0;
  int num_emt_blocks = 0;
  int num_motion_blocks = 0;
  bool gauge_fixed_by_constraints = false;  // true when the BAVis gauge constraints were applied
  // sqrt(trace(Cov_pi)) / |pi| at the solution (plane_observability.h) when options.plane_std
  // and pi is free with EMT priors, per-pair blocks; NaN otherwise; inf: pi unobservable.
  double plane_relative_std = std::numeric_limits<double>::quiet_NaN();
  double plane_std_time_s = 0.0;  // the time plane_relative_std took (0 when not computed)
  // Frames whose C_p block the motion gate released in this solve, in order
  // (options.motion_gate_chi2). The times, iterations and final values cover every round.
  std::vector<int> motion_released_ids;
};

class BundleAdjuster {
 public:
  using Pose = Vector6d;
  using Points = Eigen::Matrix<double, Eigen::Dynamic, 2>;

  // camera_matrix: K, finite and invertible. Throws std::invalid_argument.
  explicit BundleAdjuster(const Eigen::Matrix3d& camera_matrix,
                          const BundleAdjusterOptions& options = BundleAdjusterOptions());
  BundleAdjuster(const BundleAdjuster&) = delete;
  BundleAdjuster& operator=(const BundleAdjuster&) = delete;

  // Adds a frame with its initial pose (cam_from_world) and optional EMT measurement.
  // motion_ratio, motion_sigma_scale: timing of the constant-velocity prior linking frames
  // id-2, id-1, id (see ConstantVelocityCostFunctor; estimation/motion.py motion_timing):
  // 1, 1 for evenly spaced frames.
  void AddFrame(int frame_id, const Pose& cam_from_world,
                const std::optional<Pose>& emt_measurement = std::nullopt,
                double motion_ratio = 1.0, double motion_sigma_scale = 1.0);
  // Adds the N >= 1 correspondences of a pair, pixels; row i of points_m maps to row i of points_l
  // (transfer m -> l). Frames must exist (std::out_of_range otherwise) and differ.
  void AddPair(int frame_l, int frame_m, const Points& points_l, const Points& points_m);
  void SetPlane(const Eigen::Vector3d& plane);
  void SetPose(int frame_id, const Pose& cam_from_world);
  void SetConstantFrame(int frame_id, bool constant = true);
  // Holds the plane constant during Solve() (or frees it again): poses adjusted to a given pi.
  void SetConstantPlane(bool constant = true);

  SolveSummary Solve();

  std::vector<int> FrameIds() const;
  // All frame ids (ascending) and their poses, read under one lock.
  std::vector<std::pair<int, Pose>> Poses() const;
  Pose GetPose(int frame_id) const;
  Eigen::Vector3d Plane() const;
  bool HasPlane() const;
  int NumFrames() const;
  int NumPairs() const;
  int NumCorrespondences() const;
  const BundleAdjusterOptions& options() const { return options_; }
  const Eigen::Matrix3d& camera_matrix() const { return camera_matrix_; }

 private:
  struct Frame {
    std::array<double, kPoseSize> pose{};  // Ceres parameter block; std::map keeps it in place
    std::optional<Pose> emt_measurement;
    bool constant = false;
    double motion_ratio = 1.0;
    double motion_sigma_scale = 1.0;
  };
  struct Pair {
    int frame_l = 0;
    int frame_m = 0;
    Eigen::Matrix<double, 2, Eigen::Dynamic> points_l;
    Eigen::Matrix<double, 2, Eigen::Dynamic> points_m;
  };

  Frame& FindFrame(int frame_id, const char* what);
  const Frame& FindFrame(int frame_id, const char* what) const;

  mutable std::mutex mutex_;  // guards everything below
  Eigen::Matrix3d camera_matrix_;
  BundleAdjusterOptions options_;
  std::map<int, Frame> frames_;
  std::vector<Pair> pairs_;
  std::array<double, kPlaneSize> plane_{};
  bool plane_set_ = false;
  bool plane_constant_ = false;
};

}  // namespace fusedmosaic
