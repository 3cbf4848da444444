#include "fusedmosaic/problem/bundle_adjuster.h"

#include <ceres/loss_function.h>
#include <ceres/problem.h>
#include <ceres/solver.h>
#include <ceres/sphere_manifold.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <limits>
#include <memory>
#include <set>
#include <stdexcept>
#include <string>

#include "fusedmosaic/problem/motion_gate.h"
#include "fusedmosaic/problem/plane_observability.h"
#include "fusedmosaic/util/format.h"

namespace fusedmosaic {
namespace {

// The solver behind linear_solver = "auto", chosen by bench/bench_solvers.py
// (bench/results/solvers.json; 150 frames, 1000 pairs, 70 points per pair, BA+EMT, 2 threads on
// shared cores, per-pair blocks, median of interleaved runs): sparse_schur 0.28 s (best run
// 0.21 s), sparse_normal_cholesky 0.29 s (0.22 s), dense_schur 0.32 s, iterative_schur 2.0 s;
// dense_qr / dense_normal_cholesky need a dense 140k x 903 Jacobian and take 7-15 s even with
// 10 points per pair. sparse_schur and sparse_normal_cholesky are within a few percent.
constexpr ceres::LinearSolverType kAutoLinearSolver = ceres::SPARSE_SCHUR;

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

ceres::LinearSolverType LinearSolverFromString(const std::string& name) {
  if (name == "auto") return kAutoLinearSolver;
  static const char* const kAllowed[] = {
      "dense_schur", "sparse_schur",          "sparse_normal_cholesky",
      "dense_qr",    "dense_normal_cholesky", "iterative_schur"};
  for (const char* allowed : kAllowed) {
    if (name == allowed) {
      ceres::LinearSolverType type;
      std::string upper = name;
      std::transform(upper.begin(), upper.end(), upper.begin(),
                     [](unsigned char c) { return static_cast<char>(std::toupper(c)); });
      if (ceres::StringToLinearSolverType(upper, &type)) return type;
    }
  }
  throw std::invalid_argument(
      "linear_solver: expected 'auto', 'dense_schur', 'sparse_schur', 'sparse_normal_cholesky', "
      "'dense_qr', 'dense_normal_cholesky' or 'iterative_schur', got '" +
      name + "'");
}

ceres::TrustRegionStrategyType TrustRegionFromString(const std::string& name) {
  if (name == "levenberg_marquardt") return ceres::LEVENBERG_MARQUARDT;
  if (name == "dogleg") return ceres::DOGLEG;
  throw std::invalid_argument("trust_region: expected 'levenberg_marquardt' or 'dogleg', got '" +
                              name + "'");
}

void CheckPositive(double value, const char* name) {
  if (!(std::isfinite(value) && value > 0)) {
    throw std::invalid_argument(std::string(name) + ": must be finite and > 0, got " +
                                FormatDouble(value));
  }
}

void CheckSigma(const Vector6d& sigma, const char* name) {
  for (int i = 0; i < kPoseSize; ++i) {
    if (!(std::isfinite(sigma[i]) && sigma[i] > 0)) {
      throw std::invalid_argument(std::string(name) + "[" + std::to_string(i) +
                                  "]: standard deviations must be finite and > 0, got " +
                                  FormatDouble(sigma[i]));
    }
  }
}

void CheckFinite(const double* values, int n, const std::string& name) {
  for (int i = 0; i < n; ++i) {
    if (!std::isfinite(values[i])) {
      throw std::invalid_argument(name + ": contains NaN or infinite values (index " +
                                  std::to_string(i) + ")");
    }
  }
}

// Total cost (Ceres convention) of a subset of residual blocks at the current parameters.
double EvaluateCost(ceres::Problem& problem, const std::vector<ceres::ResidualBlockId>& blocks,
                    int num_threads) {
  if (blocks.empty()) return 0.0;
  ceres::Problem::EvaluateOptions options;
  options.residual_blocks = blocks;
  options.apply_loss_function = true;
  options.num_threads = num_threads;
  double cost = 0.0;
  // A failed evaluation (a camera on the plane) is no cost of 0.
  if (!problem.Evaluate(options, &cost, nullptr, nullptr, nullptr)) {
    return std::numeric_limits<double>::quiet_NaN();
  }
  return cost;
}

}  // namespace

ceres::Solver::Options SolverOptionsFor(const BundleAdjusterOptions& options,
                                        ceres::LinearSolverType linear_solver) {
  ceres::Solver::Options so;
  so.linear_solver_type = linear_solver;
  so.max_num_iterations = options.max_iterations;
  so.function_tolerance = options.function_tolerance;
  so.gradient_tolerance = options.gradient_tolerance;
  so.parameter_tolerance = options.parameter_tolerance;
  so.num_threads = options.num_threads;
  so.logging_type = ceres::SILENT;
  so.minimizer_progress_to_stdout = false;
  so.trust_region_strategy_type = TrustRegionFromString(options.trust_region);
  return so;
}

int CeresIterations(const ceres::Solver::Summary& summary) {
  return std::max(0, static_cast<int>(summary.iterations.size()) - 1);
}

double CeresCost(double cost) { return cost < 0 ? std::numeric_limits<double>::quiet_NaN() : cost; }

void BundleAdjusterOptions::Validate() const {
  CheckPositive(sigma_v_px, "sigma_v_px");
  CheckSigma(emt_sigma, "emt_sigma");
  CheckSigma(motion_sigma, "motion_sigma");
  if (!(motion_gate_chi2 > 0)) {  // inf allowed: no gate
    throw std::invalid_argument("motion_gate_chi2: must be > 0 (inf: no gate), got " +
                                FormatDouble(motion_gate_chi2));
  }
  RobustLossFromString(loss);
  CheckPositive(loss_scale_px, "loss_scale_px");
  LinearSolverFromString(linear_solver);
  if (TrustRegionFromString(trust_region) == ceres::DOGLEG &&
      LinearSolverFromString(linear_solver) == ceres::ITERATIVE_SCHUR) {
    throw std::invalid_argument(
        "trust_region: 'dogleg' needs a factorising linear solver, not 'iterative_schur'");
  }
  if (residual_blocks != "per_pair" && residual_blocks != "per_point") {
    throw std::invalid_argument("residual_blocks: expected 'per_pair' or 'per_point', got '" +
                                residual_blocks + "'");
  }
  if (max_iterations < 1) {
    throw std::invalid_argument("max_iterations: must be >= 1, got " +
                                std::to_string(max_iterations));
  }
  CheckPositive(function_tolerance, "function_tolerance");
  CheckPositive(gradient_tolerance, "gradient_tolerance");
  CheckPositive(parameter_tolerance, "parameter_tolerance");
  if (num_threads < 1) {
    throw std::invalid_argument("num_threads: must be >= 1, got " + std::to_string(num_threads));
  }
}

BundleAdjuster::BundleAdjuster(const Eigen::Matrix3d& camera_matrix,
                               const BundleAdjusterOptions& options)
    : camera_matrix_(camera_matrix), options_(options) {
  CheckFinite(camera_matrix.data(), 9, "camera_matrix");
  const double det = camera_matrix.determinant();
  if (!(std::abs(det) > 1e-12 * std::pow(camera_matrix.norm(), 3))) {
    throw std::invalid_argument("camera_matrix: matrix is singular");
  }
  options_.Validate();
}

BundleAdjuster::Frame& BundleAdjuster::FindFrame(int frame_id, const char* what) {
  auto it = frames_.find(frame_id);
  if (it == frames_.end()) {
    throw std::out_of_range(std::string(what) + ": unknown frame id " + std::to_string(frame_id) +
                            " (call add_frame first)");
  }
  return it->second;
}

const BundleAdjuster::Frame& BundleAdjuster::FindFrame(int frame_id, const char* what) const {
  return const_cast<BundleAdjuster*>(this)->FindFrame(frame_id, what);
}

void BundleAdjuster::AddFrame(int frame_id, const Pose& cam_from_world,
                              const std::optional<Pose>& emt_measurement, double motion_ratio,
                              double motion_sigma_scale) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (frames_.count(frame_id)) {
    throw std::invalid_argument("add_frame: frame id " + std::to_string(frame_id) +
                                " already added (use set_pose to change its pose)");
  }
  CheckFinite(cam_from_world.data(), kPoseSize, "cam_from_world");
  if (emt_measurement) CheckFinite(emt_measurement->data(), kPoseSize, "emt_measurement");
  CheckMotionTiming(motion_ratio, motion_sigma_scale, "add_frame");
  Frame frame;
  std::copy(cam_from_world.data(), cam_from_world.data() + kPoseSize, frame.pose.begin());
  frame.emt_measurement = emt_measurement;
  frame.motion_ratio = motion_ratio;
  frame.motion_sigma_scale = motion_sigma_scale;
  frames_.emplace(frame_id, std::move(frame));
}

void BundleAdjuster::AddPair(int frame_l, int frame_m, const Points& points_l,
                             const Points& points_m) {
  std::lock_guard<std::mutex> lock(mutex_);
  FindFrame(frame_l, "add_pair: frame_l");
  FindFrame(frame_m, "add_pair: frame_m");
  if (frame_l == frame_m) {
    throw std::invalid_argument("add_pair: frame_l and frame_m are the same frame (" +
                                std::to_string(frame_l) + ")");
  }
  if (points_l.rows() != points_m.rows()) {
    throw std::invalid_argument("add_pair: points_l has " + std::to_string(points_l.rows()) +
                                " rows but points_m has " + std::to_string(points_m.rows()));
  }
  if (points_l.rows() < 1) {
    throw std::invalid_argument("add_pair: needs at least 1 correspondence, got 0");
  }
  for (Eigen::Index i = 0; i < points_l.rows(); ++i) {
    if (!points_l.row(i).allFinite() || !points_m.row(i).allFinite()) {
      throw std::invalid_argument("add_pair: row " + std::to_string(i) +
                                  " of points_l/points_m contains NaN or infinite values");
    }
  }
  Pair pair;
  pair.frame_l = frame_l;
  pair.frame_m = frame_m;
  pair.points_l = points_l.transpose();
  pair.points_m = points_m.transpose();
  pairs_.push_back(std::move(pair));
}

void BundleAdjuster::SetPlane(const Eigen::Vector3d& plane) {
  std::lock_guard<std::mutex> lock(mutex_);
  CheckFinite(plane.data(), kPlaneSize, "plane");
  if (!(plane.norm() > 1e-12)) {
    throw std::invalid_argument(
        "plane: pi = n/d must be non-zero (pi = 0 is the plane at infinity)");
  }
  std::copy(plane.data(), plane.data() + kPlaneSize, plane_.begin());
  plane_set_ = true;
}

void BundleAdjuster::SetConstantPlane(bool constant) {
  std::lock_guard<std::mutex> lock(mutex_);
  plane_constant_ = constant;
}

void BundleAdjuster::SetPose(int frame_id, const Pose& cam_from_world) {
  std::lock_guard<std::mutex> lock(mutex_);
  Frame& frame = FindFrame(frame_id, "set_pose");
  CheckFinite(cam_from_world.data(), kPoseSize, "pose");
  std::copy(cam_from_world.data(), cam_from_world.data() + kPoseSize, frame.pose.begin());
}

void BundleAdjuster::SetConstantFrame(int frame_id, bool constant) {
  std::lock_guard<std::mutex> lock(mutex_);
  FindFrame(frame_id, "set_constant_frame").constant = constant;
}

std::vector<int> BundleAdjuster::FrameIds() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<int> ids;
  ids.reserve(frames_.size());
  for (const auto& [id, frame] : frames_) ids.push_back(id);
  return ids;
}

std::vector<std::pair<int, BundleAdjuster::Pose>> BundleAdjuster::Poses() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<std::pair<int, Pose>> out;
  out.reserve(frames_.size());
  for (const auto& [id, frame] : frames_) {
    out.emplace_back(id, Eigen::Map<const Pose>(frame.pose.data()));
  }
  return out;
}

BundleAdjuster::Pose BundleAdjuster::GetPose(int frame_id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  return Eigen::Map<const Pose>(FindFrame(frame_id, "pose").pose.data());
}

Eigen::Vector3d BundleAdjuster::Plane() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!plane_set_) throw std::invalid_argument("plane: not set (call set_plane first)");
  return Eigen::Map<const Eigen::Vector3d>(plane_.data());
}

bool BundleAdjuster::HasPlane() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return plane_set_;
}

int BundleAdjuster::NumFrames() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(frames_.size());
}

int BundleAdjuster::NumPairs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(pairs_.size());
}

int BundleAdjuster::NumCorrespondences() const {
  std::lock_guard<std::mutex> lock(mutex_);
  int n = 0;
  for (const Pair& pair : pairs_) n += static_cast<int>(pair.points_l.cols());
  return n;
}

SolveSummary BundleAdjuster::Solve() {
  std::lock_guard<std::mutex> lock(mutex_);
  if (frames_.empty()) throw std::invalid_argument("solve: no frames (call add_frame first)");
  if (!pairs_.empty() && !plane_set_) {
    throw std::invalid_argument("solve: plane not set (call set_plane before solving pairs)");
  }
  const RobustLoss loss = RobustLossFromString(options_.loss);
  const bool per_point = options_.residual_blocks == "per_point";

  ceres::Problem problem;
  std::vector<ceres::ResidualBlockId> visual_blocks, emt_blocks;
  MotionBlocks motion;
  double* plane = plane_.data();

  for (const Pair& pair : pairs_) {
    double* pose_l = frames_.at(pair.frame_l).pose.data();
    double* pose_m = frames_.at(pair.frame_m).pose.data();
    if (!per_point) {
      // Per-point robustness inside the block (visual_transfer.h).
      visual_blocks.push_back(problem.AddResidualBlock(
          CreateVisualTransferCost(
              VisualTransferCostFunctor(camera_matrix_, pair.points_l, pair.points_m,
                                        options_.sigma_v_px, loss, options_.loss_scale_px),
              nullptr, nullptr, options_.condense_pairs),
          nullptr, pose_l, pose_m, plane));
      continue;
    }
    // One block per correspondence, robustness by a Ceres LossFunction (scale in sigma_v units).
    const double a = options_.loss_scale_px / options_.sigma_v_px;
    for (Eigen::Index i = 0; i < pair.points_l.cols(); ++i) {
      ceres::LossFunction* loss_function = nullptr;
      if (loss == RobustLoss::kHuber) loss_function = new ceres::HuberLoss(a);
      if (loss == RobustLoss::kCauchy) loss_function = new ceres::CauchyLoss(a);
      visual_blocks.push_back(problem.AddResidualBlock(
          VisualTransferCostFunctor::Create(camera_matrix_, pair.points_l.col(i),
                                            pair.points_m.col(i), options_.sigma_v_px),
          loss_function, pose_l, pose_m, plane));
    }
  }

  if (options_.use_emt) {
    for (auto& [id, frame] : frames_) {
      if (!frame.emt_measurement) continue;
      emt_blocks.push_back(problem.AddResidualBlock(
          PosePriorCostFunctor::Create(*frame.emt_measurement, options_.emt_sigma), nullptr,
          frame.pose.data()));
    }
  }

  if (options_.use_motion_prior) {
    std::set<int> visual;  // frames with a pair: the motion gate judges their C_p only
    for (const Pair& pair : pairs_) visual.insert({pair.frame_l, pair.frame_m});
    for (auto& [id, frame] : frames_) {
      if (id < std::numeric_limits<int>::min() + 2) continue;
      auto km1 = frames_.find(id - 1);
      auto km2 = frames_.find(id - 2);
      if (km1 == frames_.end() || km2 == frames_.end()) continue;
      if (!MotionPriorLinked(frame.motion_sigma_scale)) continue;
      motion.Add(problem.AddResidualBlock(
                     ConstantVelocityCostFunctor::Create(
                         options_.motion_sigma * frame.motion_sigma_scale, frame.motion_ratio),
                     nullptr, km2->second.pose.data(), km1->second.pose.data(),
                     frame.pose.data()),
                 id,
                 MotionJudged(visual.count(id) > 0, km2->second.emt_measurement.has_value(),
                              km1->second.emt_measurement.has_value(),
                              frame.emt_measurement.has_value()));
    }
  }

  if (problem.NumResidualBlocks() == 0) {
    throw std::invalid_argument(
        "solve: nothing to optimise (no pairs, and no EMT measurements or motion-prior triples "
        "enabled)");
  }

  // Frames held constant by the user, among those in the problem.
  std::vector<int> constant_ids;
  int first_id = 0;
  bool have_first = false;
  for (auto& [id, frame] : frames_) {
    if (!problem.HasParameterBlock(frame.pose.data())) continue;
    if (!have_first) {
      first_id = id;
      have_first = true;
    }
    if (frame.constant) {
      problem.SetParameterBlockConstant(frame.pose.data());
      constant_ids.push_back(id);
    }
  }

  if (plane_constant_ && problem.HasParameterBlock(plane)) {
    problem.SetParameterBlockConstant(plane);
  }

  // BAVis gauge (see the header): without EMT priors hold the first frame and |pi|.
  SolveSummary out;
  if (emt_blocks.empty()) {
    out.gauge_fixed_by_constraints = true;
    if (constant_ids.empty()) {
      problem.SetParameterBlockConstant(frames_.at(first_id).pose.data());
      constant_ids.push_back(first_id);
    }
    if (constant_ids.size() < 2 && problem.HasParameterBlock(plane) && !plane_constant_) {
      problem.SetManifold(plane, new ceres::SphereManifold<kPlaneSize>());
    }
  }

  ceres::Solver::Options solver_options =
      SolverOptionsFor(options_, LinearSolverFromString(options_.linear_solver));
  std::string error;
  if (!solver_options.IsValid(&error)) throw std::invalid_argument("solve: " + error);

  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  out.initial_cost = CeresCost(summary.initial_cost);
  int iterations = CeresIterations(summary);
  double solve_time_s = summary.total_time_in_seconds;
  // The motion gate (motion_gate.h), in rounds, each followed by a solve; for this solve only.
  int releases_left =
      MaxMotionReleases(static_cast<int>(motion.blocks.size()), options_.motion_gate_chi2);
  while (releases_left > 0) {
    const std::vector<int> released =
        ReleaseMotionBlocks(&problem, &motion, options_.motion_gate_chi2, releases_left);
    if (released.empty()) break;
    releases_left -= static_cast<int>(released.size());
    out.motion_released_ids.insert(out.motion_released_ids.end(), released.begin(),
                                   released.end());
    ceres::Solve(solver_options, &problem, &summary);
    iterations += CeresIterations(summary);
    solve_time_s += summary.total_time_in_seconds;
  }

  out.iterations = iterations;
  out.final_cost = CeresCost(summary.final_cost);
  out.visual_cost = EvaluateCost(problem, visual_blocks, options_.num_threads);
  out.emt_cost = EvaluateCost(problem, emt_blocks, options_.num_threads);
  out.motion_cost = EvaluateCost(problem, motion.blocks, options_.num_threads);
  out.solve_time_s = solve_time_s;
  out.termination = ceres::TerminationTypeToString(summary.termination_type);
  out.message = summary.message;
  out.full_report = summary.FullReport();
  out.linear_solver = Lower(ceres::LinearSolverTypeToString(summary.linear_solver_type_used));
  out.num_residual_blocks = summary.num_residual_blocks;
  out.num_residuals = summary.num_residuals;
  out.num_parameters = summary.num_parameters;
  out.num_free_parameters = summary.num_effective_parameters_reduced;
  out.num_visual_blocks = static_cast<int>(visual_blocks.size());
  out.num_emt_blocks = static_cast<int>(emt_blocks.size());
  out.num_motion_blocks = static_cast<int>(motion.blocks.size());
  if (options_.plane_std && !per_point && !out.gauge_fixed_by_constraints &&
      problem.HasParameterBlock(plane) && !problem.IsParameterBlockConstant(plane)) {
    std::set<int> paired;
    for (const Pair& pair : pairs_) paired.insert({pair.frame_l, pair.frame_m});
    std::vector<double*> free_poses;
    for (auto& [id, frame] : frames_) {
      double* pose = frame.pose.data();
      if (options_.plane_std_paired_only && paired.count(id) == 0) continue;
      if (problem.HasParameterBlock(pose) && !problem.IsParameterBlockConstant(pose)) {
        free_poses.push_back(pose);
      }
    }
    const auto start = std::chrono::steady_clock::now();
    out.plane_relative_std = PlaneRelativeStd(&problem, plane, free_poses,
                                              Eigen::Map<const Eigen::Vector3d>(plane).norm());
    out.plane_std_time_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  }
  return out;
}

}  // namespace fusedmosaic
