#include "fusedmosaic/problem/sliding_window.h"

#include <Eigen/Eigenvalues>
#include <ceres/problem.h>
#include <ceres/solver.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <stdexcept>
#include <string>

#include "fusedmosaic/problem/motion_gate.h"
#include "fusedmosaic/problem/plane_observability.h"
#include "fusedmosaic/residuals/constant_velocity.h"
#include "fusedmosaic/residuals/pose_prior.h"
#include "fusedmosaic/residuals/visual_transfer.h"
#include "fusedmosaic/util/format.h"

namespace fusedmosaic {
namespace {

// "auto" for the window. A step has chi_e * 6 + 3 free parameters (21 with the SYN preset) and
// ~13k residuals, most of them (pairs of two fixed cameras) touching only pi. With the 2N
// residuals per pair the dense solvers paid for the full 13k x 21 Jacobian (J^T J, QR), the
// block-sparse J^T J did not: bench/bench_sequential.py on a recorded SYN stream (median per
// step, 1 thread, fixed cameras folded, idle 2-core EPYC): sparse_normal_cholesky 3.0 ms <
// dense_schur 3.4 ~ sparse_schur 3.4 < dense_normal_cholesky 5.8 < dense_qr 10.5 ms. With the
// condensed pair blocks (~400 residuals) they are close (2-core Xeon replay of 400 frames:
// dense_schur 3.71 ~ sparse_normal_cholesky 3.74 < dense_normal_cholesky 3.83 < dense_qr 3.99
// ms). Ceres on 2 threads now takes ~0.5 ms off (the evaluation); the window is given 1
// (estimation/sequential.py): a parallel evaluation sums in a run-dependent order.
constexpr ceres::LinearSolverType kWindowAutoSolver = ceres::SPARSE_NORMAL_CHOLESKY;

ceres::LinearSolverType WindowLinearSolver(const std::string& name) {
  if (name == "auto") return kWindowAutoSolver;
  std::string upper = name;
  std::transform(upper.begin(), upper.end(), upper.begin(),
                 [](unsigned char c) { return static_cast<char>(std::toupper(c)); });
  ceres::LinearSolverType type;
  if (!ceres::StringToLinearSolverType(upper, &type)) {
    throw std::invalid_argument("linear_solver: unknown solver '" + name + "'");
  }
  return type;
}

SlidingWindow::Pose ToVector(const std::array<double, kPoseSize>& a) {
  return Eigen::Map<const SlidingWindow::Pose>(a.data());
}

void CheckPose(const SlidingWindow::Pose& pose, const char* name) {
  if (!pose.allFinite()) {
    throw std::invalid_argument(std::string(name) + ": contains NaN or infinite values");
  }
}

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

}  // namespace

void SlidingWindowOptions::Validate() const {
  if (num_new < 1) {
    throw std::invalid_argument("num_new: must be >= 1, got " + std::to_string(num_new));
  }
  if (window_size < num_new) {
    throw std::invalid_argument("window_size: must be >= num_new (" + std::to_string(num_new) +
                                "), got " + std::to_string(window_size));
  }
  if (costs.use_motion_prior && window_size - num_new < 2) {
    // C_p (Eq. 27) links the first new camera to its two predecessors, the last two fixed
    // cameras; Forget keeps only the window's window_size - num_new, so with fewer an older
    // camera could silently stand in for a forgotten predecessor.
    throw std::invalid_argument(
        "window_size: must be >= num_new + 2 (" + std::to_string(num_new + 2) +
        ") with the constant-velocity prior (costs.use_motion_prior): C_p links each new camera "
        "to its two predecessors, which the window must hold fixed; got window_size " +
        std::to_string(window_size) + ", num_new " + std::to_string(num_new));
  }
  if (!(plane_max_relative_std >= 0.0) || !std::isfinite(plane_max_relative_std)) {
    throw std::invalid_argument("plane_max_relative_std: must be finite and >= 0, got " +
                                FormatDouble(plane_max_relative_std));
  }
  costs.Validate();
  WindowLinearSolver(costs.linear_solver);
}

SlidingWindow::SlidingWindow(const Eigen::Matrix3d& camera_matrix,
                             const SlidingWindowOptions& options)
    : camera_matrix_(camera_matrix), options_(options) {
  if (!camera_matrix.allFinite() ||
      !(std::abs(camera_matrix.determinant()) > 1e-12 * std::pow(camera_matrix.norm(), 3))) {
    throw std::invalid_argument("camera_matrix: must be finite and invertible");
  }
  options_.Validate();
}

SlidingWindow::Frame& SlidingWindow::FindFrame(int frame_id, const char* what) {
  auto it = frames_.find(frame_id);
  if (it == frames_.end()) {
    throw std::out_of_range(std::string(what) + ": unknown frame id " + std::to_string(frame_id));
  }
  return it->second;
}

const SlidingWindow::Frame& SlidingWindow::FindFrame(int frame_id, const char* what) const {
  return const_cast<SlidingWindow*>(this)->FindFrame(frame_id, what);
}

void SlidingWindow::AddFrame(int frame_id, const std::optional<Pose>& initial,
                             const std::optional<Pose>& emt_measurement, bool fixed,
                             double motion_ratio, double motion_sigma_scale) {
  std::lock_guard<std::mutex> lock(mutex_);
  CheckMotionTiming(motion_ratio, motion_sigma_scale, "add_frame");
  if (fixed && !initial) {
    throw std::invalid_argument("add_frame: a fixed frame needs its pose (initial)");
  }
  for (const auto& [id, f] : frames_) {
    if (fixed && !f.fixed) {
      throw std::invalid_argument("add_frame: fixed frame " + std::to_string(frame_id) +
                                  " after pending frame " + std::to_string(id));
    }
  }
  if (!frames_.empty() && frame_id <= frames_.rbegin()->first) {
    throw std::invalid_argument("add_frame: frame ids must increase; got " +
                                std::to_string(frame_id) + " after " +
                                std::to_string(frames_.rbegin()->first));
  }
  if (frames_.empty() && !initial && !emt_measurement) {
    // InitialisePending starts a frame from its initial pose, its tracker sample or the
    // prediction from its predecessors: the first frame has none of the last.
    throw std::invalid_argument(
        "add_frame: frame " + std::to_string(frame_id) +
        " is the window's first frame and has neither an initial pose nor a tracker sample "
        "(emt_measurement): it has no predecessors to be predicted from, so nothing would place "
        "it; give it one of them");
  }
  Frame frame;
  if (initial) {
    CheckPose(*initial, "initial");
    Eigen::Map<Pose>(frame.pose.data()) = *initial;
    frame.has_initial = true;
  }
  if (emt_measurement) {
    CheckPose(*emt_measurement, "emt_measurement");
    frame.emt_measurement = emt_measurement;
  }
  frame.fixed = fixed;
  frame.motion_ratio = motion_ratio;
  frame.motion_sigma_scale = motion_sigma_scale;
  frames_.emplace(frame_id, std::move(frame));
}

void SlidingWindow::SetEmtSigmaScale(int frame_id, double scale) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!(std::isfinite(scale) && scale >= 1.0)) {
    throw std::invalid_argument("scale: must be finite and >= 1, got " + FormatDouble(scale));
  }
  FindFrame(frame_id, "set_emt_sigma_scale").emt_sigma_scale = scale;
}

void SlidingWindow::SetSigmaV(double sigma_v_px) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!(std::isfinite(sigma_v_px) && sigma_v_px > 0.0)) {
    throw std::invalid_argument("sigma_v_px: must be finite and > 0, got " +
                                FormatDouble(sigma_v_px));
  }
  options_.costs.sigma_v_px = sigma_v_px;
}

double SlidingWindow::sigma_v_px() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return options_.costs.sigma_v_px;
}

void SlidingWindow::DropEmtMeasurement(int frame_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  Frame& frame = FindFrame(frame_id, "drop_emt_measurement");
  if (!frame.fixed && frame_id == frames_.begin()->first) {
    // Its next step would start it from the prediction of its predecessors (its initial pose
    // is not kept, as for any frame): the first frame has none.
    throw std::invalid_argument(
        "drop_emt_measurement: frame " + std::to_string(frame_id) +
        " is the window's first frame and still pending: without its tracker sample it would "
        "have no starting pose (no predecessors to predict it from, and its initial pose is "
        "not kept)");
  }
  frame.emt_measurement.reset();
  frame.emt_sigma_scale = 1.0;
  frame.has_initial = false;  // (InitialisePending predicts it at its next step)
}

void SlidingWindow::CheckKeyframes(const std::vector<int>& keyframe_ids,
                                   const std::vector<int>& free_ids, const char* what) const {
  for (int id : keyframe_ids) {
    const Frame& f = FindFrame(id, (std::string(what) + " keyframe").c_str());
    if (!f.fixed) {
      throw std::invalid_argument(std::string(what) + ": keyframe " + std::to_string(id) +
                                  " is not yet fixed");
    }
    if (std::count(free_ids.begin(), free_ids.end(), id)) {
      throw std::invalid_argument(std::string(what) + ": keyframe " + std::to_string(id) +
                                  " is among the frames this call estimates (keyframes must be "
                                  "fixed frames outside them)");
    }
  }
}

void SlidingWindow::SetMotionTiming(int frame_id, double motion_ratio,
                                    double motion_sigma_scale) {
  std::lock_guard<std::mutex> lock(mutex_);
  CheckMotionTiming(motion_ratio, motion_sigma_scale, "set_motion_timing");
  Frame& frame = FindFrame(frame_id, "set_motion_timing");
  frame.motion_ratio = motion_ratio;
  frame.motion_sigma_scale = motion_sigma_scale;
}

void SlidingWindow::AddPair(int frame_l, int frame_m, const Points& points_l,
                            const Points& points_m) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (frame_l == frame_m) throw std::invalid_argument("add_pair: frame_l == frame_m");
  if (points_l.rows() != points_m.rows() || points_l.rows() < 1) {
    throw std::invalid_argument("add_pair: points_l and points_m need the same N >= 1 rows, got " +
                                std::to_string(points_l.rows()) + " and " +
                                std::to_string(points_m.rows()));
  }
  if (!points_l.allFinite() || !points_m.allFinite()) {
    throw std::invalid_argument("add_pair: points contain NaN or infinite values");
  }
  Frame& l = FindFrame(frame_l, "add_pair frame_l");
  Frame& m = FindFrame(frame_m, "add_pair frame_m");
  const auto key = std::make_pair(frame_l, frame_m);
  auto [it, inserted] = pairs_.try_emplace(key);
  if (!inserted) num_correspondences_ -= static_cast<int>(it->second.points_l.cols());
  it->second.points_l = points_l.transpose();
  it->second.points_m = points_m.transpose();
  num_correspondences_ += static_cast<int>(points_l.rows());
  if (inserted) {
    l.pair_keys.push_back(key);
    m.pair_keys.push_back(key);
  }
}

void SlidingWindow::SetPlane(const Eigen::Vector3d& plane) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!plane.allFinite() || !(plane.norm() > 1e-12)) {
    throw std::invalid_argument("plane: must be finite and non-zero (pi = 0 is the plane at "
                                "infinity)");
  }
  Eigen::Map<Eigen::Vector3d>(plane_.data()) = plane;
  plane_set_ = true;
}

std::vector<int> SlidingWindow::WindowIdsLocked(int num_new) const {
  std::vector<int> out;
  const int wanted = std::max(0, options_.window_size - num_new);
  for (auto it = frames_.rbegin(); it != frames_.rend() && static_cast<int>(out.size()) < wanted;
       ++it) {
    if (it->second.fixed) out.push_back(it->first);
  }
  std::reverse(out.begin(), out.end());
  return out;
}

void SlidingWindow::InitialisePending(const std::vector<int>& ids) {
  for (int id : ids) {
    Frame& f = frames_.at(id);
    if (f.has_initial) continue;
    auto it = frames_.find(id);
    // (a gated sample starts from the constant-velocity prediction where there is one: Redo)
    if (f.emt_measurement && (f.emt_sigma_scale <= 1.0 || it == frames_.begin())) {
      Eigen::Map<Pose>(f.pose.data()) = *f.emt_measurement;
    } else {
      // Constant-velocity prediction (Eq. 15-16) from the two preceding cameras, if any.
      if (it == frames_.begin()) {
        throw std::invalid_argument("frame " + std::to_string(id) +
                                    ": no initial pose, no tracker sample and no predecessor");
      }
      auto prev1 = std::prev(it);
      if (prev1 == frames_.begin()) {
        f.pose = prev1->second.pose;
      } else {
        auto prev2 = std::prev(prev1);
        PredictConstantVelocity(RigidTransform<double>::FromPose(prev2->second.pose.data()),
                                RigidTransform<double>::FromPose(prev1->second.pose.data()),
                                f.motion_ratio)
            .ToPose(f.pose.data());
      }
    }
    f.has_initial = true;
  }
}

WindowStepSummary SlidingWindow::Step(const std::vector<int>& keyframe_ids, bool hold_plane) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<int> pending;
  for (const auto& [id, f] : frames_)
    if (!f.fixed) pending.push_back(id);
  if (pending.empty()) throw std::invalid_argument("step: no pending frame (call add_frame)");
  if (!plane_set_) throw std::invalid_argument("step: set_plane must be called first");
  CheckKeyframes(keyframe_ids, pending, "step");  // (before anything changes)
  return Solve(pending, keyframe_ids, hold_plane);
}

WindowStepSummary SlidingWindow::Redo(const std::vector<int>& frame_ids,
                                      const std::vector<int>& keyframe_ids, bool hold_plane) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (frame_ids.empty()) throw std::invalid_argument("redo: frame_ids is empty");
  std::vector<int> ids = frame_ids;
  std::sort(ids.begin(), ids.end());
  for (size_t i = 0; i < ids.size(); ++i) {
    FindFrame(ids[i], "redo");
    if (i > 0 && ids[i] == ids[i - 1]) {
      // (each would add its frame's C_EMT and C_p blocks again)
      throw std::invalid_argument("redo: frame " + std::to_string(ids[i]) +
                                  " appears more than once in frame_ids");
    }
  }
  // The redone frames must be the last ones, as in the step they redo: the window is the fixed
  // cameras before them, and their C_p terms link them to their predecessors. A frame after
  // them left out would join the window as a camera of the past; a pending one before them
  // (never estimated: its pose unset) would be held constant as their predecessor, and then be
  // estimated after them. The caller's redo of a step's held frames also re-estimates the
  // frames added since (pending): every frame from the first redone one on.
  for (auto it = frames_.find(ids.front()); it != frames_.end(); ++it) {
    if (!std::binary_search(ids.begin(), ids.end(), it->first)) {
      throw std::invalid_argument("redo: frame_ids must be the last frames, but frame " +
                                  std::to_string(it->first) + " after frame " +
                                  std::to_string(ids.front()) + " is not among them");
    }
  }
  for (auto it = frames_.begin(); it->first != ids.front(); ++it) {
    if (!it->second.fixed) {
      throw std::invalid_argument("redo: frame " + std::to_string(it->first) +
                                  " before frame_ids is still pending (step it first)");
    }
  }
  if (!plane_set_) throw std::invalid_argument("redo: set_plane must be called first");
  CheckKeyframes(keyframe_ids, ids, "redo");  // (before anything changes)
  if (ids.front() == frames_.begin()->first && !frames_.begin()->second.emt_measurement) {
    // (InitialisePending would refuse it after the loop below had made every frame pending)
    throw std::invalid_argument(
        "redo: frame " + std::to_string(ids.front()) +
        " is the window's first frame and has no tracker sample: a redo starts each frame "
        "again from its sample or the constant-velocity prediction of its predecessors (not "
        "from its initial pose or last estimate), and it has neither");
  }
  // Nothing below throws before Solve's InitialisePending, which the checks above satisfy: a
  // refused call leaves the window as it was.
  for (int id : ids) {
    Frame& f = frames_.at(id);
    // Started again as a step starts them (InitialisePending), not from the solve being redone:
    // from the tracker sample, or the constant-velocity prediction for a frame without one and
    // for a gated sample (down-weighted: it disagreed with the images, no starting point).
    // A sample 124 deg off, gated, redone from its sample and from the first solve's poses of
    // the untracked frames beside it, settled far from the images: every later frame 100-1e5 px
    // off, all "placed".
    f.has_initial = false;
    f.fixed = false;
  }
  return Solve(ids, keyframe_ids, hold_plane);
}

WindowStepSummary SlidingWindow::Solve(std::vector<int> free_ids,
                                       const std::vector<int>& keyframe_ids, bool hold_plane) {
  const auto t_start = std::chrono::steady_clock::now();
  std::sort(free_ids.begin(), free_ids.end());
  if (!plane_set_) throw std::invalid_argument("step: set_plane must be called first");
  const BundleAdjusterOptions& c = options_.costs;
  InitialisePending(free_ids);

  WindowStepSummary out = SolveStep(free_ids, keyframe_ids, hold_plane);

  for (int id : free_ids) {
    Frame& f = frames_.at(id);
    f.fixed = true;
    if (f.emt_measurement) {
      Pose r;  // x - z as C_EMT takes it (pose_prior.h), nominal Sigma_EMT
      PoseDifference(f.pose.data(), f.emt_measurement->data(), r.data());
      out.emt_mahalanobis2.push_back(r.cwiseQuotient(c.emt_sigma).squaredNorm());
    } else {
      out.emt_mahalanobis2.push_back(std::numeric_limits<double>::quiet_NaN());
    }
  }
  out.step_time_s = Seconds(t_start);
  return out;
}

WindowStepSummary SlidingWindow::SolveStep(const std::vector<int>& free_ids,
                                           const std::vector<int>& keyframe_ids,
                                           bool hold_plane) {
  const BundleAdjusterOptions& c = options_.costs;
  const double plane_norm_before = Eigen::Map<const Eigen::Vector3d>(plane_.data()).norm();
  WindowStepSummary out;
  out.frame_ids = free_ids;
  out.fixed_ids = WindowIdsLocked(static_cast<int>(free_ids.size()));
  // Window ids are the fixed cameras preceding the free ones; in Redo the free ones are the
  // last cameras, so the same rule applies.
  std::set<int> in_problem(free_ids.begin(), free_ids.end());
  for (int id : out.fixed_ids) in_problem.insert(id);
  // Fixed cameras paired with a new one (e.g. EMT-predicted revisits matched by the caller)
  // join the step as constants, so their pairs enter C_v (the set W of Eq. 25).
  for (int id : free_ids) {
    for (const auto& key : frames_.at(id).pair_keys) {
      const int other = key.first == id ? key.second : key.first;
      if (frames_.at(other).fixed) in_problem.insert(other);
    }
  }
  for (int id : keyframe_ids) {  // (known and fixed: CheckKeyframes, before any change)
    if (in_problem.insert(id).second) out.keyframe_ids.push_back(id);
  }

  ceres::Problem problem;
  std::vector<ceres::ResidualBlockId> visual_blocks, emt_blocks;
  MotionBlocks motion;
  const RobustLoss loss = RobustLossFromString(c.loss);
  const bool per_point = c.residual_blocks == "per_point";

  // Role of a camera in this step, for the residual counts of the summary.
  enum class Role { kFree, kWindow, kKeyframe, kTemporal, kLoop };
  const std::set<int> keyframe_set(out.keyframe_ids.begin(), out.keyframe_ids.end());
  std::set<int> temporal;  // the window_size - 1 frames before the first free one
  for (auto it = frames_.find(free_ids.front());
       it != frames_.begin() && static_cast<int>(temporal.size()) < options_.window_size - 1;) {
    temporal.insert((--it)->first);
  }
  auto role = [&](int id) {
    if (std::binary_search(free_ids.begin(), free_ids.end(), id)) return Role::kFree;
    if (std::count(out.fixed_ids.begin(), out.fixed_ids.end(), id)) return Role::kWindow;
    if (keyframe_set.count(id)) return Role::kKeyframe;
    if (temporal.count(id)) return Role::kTemporal;
    return Role::kLoop;
  };

  // C_v (Eq. 25): every stored pair with both cameras in the step.
  std::set<std::pair<int, int>> used;
  for (int id : in_problem) {
    for (const auto& key : frames_.at(id).pair_keys) {
      if (!in_problem.count(key.first) || !in_problem.count(key.second)) continue;
      if (!used.insert(key).second) continue;
      const Pair& pair = pairs_.at(key);
      double* pose_l = frames_.at(key.first).pose.data();
      double* pose_m = frames_.at(key.second).pose.data();
      const int n = static_cast<int>(pair.points_l.cols());
      out.num_correspondences += n;
      const Role role_l = role(key.first), role_m = role(key.second);
      if (role_l == Role::kKeyframe || role_m == Role::kKeyframe) {
        out.num_keyframe_correspondences += n;
      } else if (role_l == Role::kLoop || role_m == Role::kLoop) {
        out.num_loop_correspondences += n;
      } else if (role_l == Role::kTemporal || role_m == Role::kTemporal) {
        out.num_temporal_correspondences += n;
      } else {
        out.num_window_correspondences += n;
      }
      if (role_l != Role::kFree && role_m != Role::kFree) out.num_fixed_pair_correspondences += n;
      const bool fold_l = options_.fold_fixed_cameras && role_l != Role::kFree;
      const bool fold_m = options_.fold_fixed_cameras && role_m != Role::kFree;
      const int blocks = per_point ? n : 1;
      for (int b = 0; b < blocks; ++b) {
        const int first = per_point ? b : 0, count = per_point ? 1 : n;
        VisualTransferCostFunctor transfer(camera_matrix_, pair.points_l.middleCols(first, count),
                                           pair.points_m.middleCols(first, count), c.sigma_v_px,
                                           loss, c.loss_scale_px);
        // Cameras held constant in the step are folded into the block as constants, so its
        // Jacobian spans only the free parameters: 9 (one new camera + pi) or 3 (pi alone, a
        // pair of two fixed cameras) columns instead of 15.
        ceres::CostFunction* cost = CreateVisualTransferCost(
            std::move(transfer), fold_l ? frames_.at(key.first).pose.data() : nullptr,
            fold_m ? frames_.at(key.second).pose.data() : nullptr,
            c.condense_pairs && !per_point);
        std::vector<double*> blocks_of_pair;
        if (!fold_l) blocks_of_pair.push_back(pose_l);
        if (!fold_m) blocks_of_pair.push_back(pose_m);
        blocks_of_pair.push_back(plane_.data());
        const ceres::ResidualBlockId block =
            problem.AddResidualBlock(cost, nullptr, blocks_of_pair);
        visual_blocks.push_back(block);
      }
    }
  }
  // C_EMT (Eq. 26) and C_p (Eq. 27) for the free cameras.
  for (int id : free_ids) {
    Frame& f = frames_.at(id);
    problem.AddParameterBlock(f.pose.data(), kPoseSize);
    if (c.use_emt && f.emt_measurement) {
      emt_blocks.push_back(problem.AddResidualBlock(
          PosePriorCostFunctor::Create(*f.emt_measurement, c.emt_sigma * f.emt_sigma_scale),
          nullptr, f.pose.data()));
    }
    if (c.use_motion_prior) {
      auto it = frames_.find(id);
      if (MotionPriorLinked(f.motion_sigma_scale) && it != frames_.begin() &&
          std::prev(it) != frames_.begin()) {
        auto prev1 = std::prev(it);
        auto prev2 = std::prev(prev1);
        motion.Add(problem.AddResidualBlock(
                       ConstantVelocityCostFunctor::Create(c.motion_sigma * f.motion_sigma_scale,
                                                           f.motion_ratio),
                       nullptr, prev2->second.pose.data(), prev1->second.pose.data(),
                       f.pose.data()),
                   id,
                   MotionJudged(std::any_of(f.pair_keys.begin(), f.pair_keys.end(),
                                            [&](const auto& key) { return used.count(key) > 0; }),
                                prev2->second.emt_measurement.has_value(),
                                prev1->second.emt_measurement.has_value(),
                                f.emt_measurement.has_value()));
        for (auto p : {prev1, prev2})
          if (!in_problem.count(p->first)) problem.SetParameterBlockConstant(p->second.pose.data());
      }
    }
  }
  for (int id : in_problem) {
    if (!std::binary_search(free_ids.begin(), free_ids.end(), id) &&
        problem.HasParameterBlock(frames_.at(id).pose.data())) {
      problem.SetParameterBlockConstant(frames_.at(id).pose.data());
    }
  }
  const bool plane_free =
      problem.HasParameterBlock(plane_.data()) && !visual_blocks.empty() && !hold_plane;
  if (problem.HasParameterBlock(plane_.data()) && !plane_free) {
    problem.SetParameterBlockConstant(plane_.data());
  }
  out.plane_held = !plane_free;
  out.num_visual_blocks = static_cast<int>(visual_blocks.size());

  if (problem.NumResidualBlocks() == 0) {
    out.termination = "NO_RESIDUALS";
    return out;
  }
  const ceres::Solver::Options so = SolverOptionsFor(c, WindowLinearSolver(c.linear_solver));
  // Runs the solver; a second run (pi held) adds its counts and times to the first's.
  auto solve = [&](bool first) {
    ceres::Solver::Summary summary;
    ceres::Solve(so, &problem, &summary);
    if (first) {
      out.initial_cost = CeresCost(summary.initial_cost);
      out.iterations = 0;
    }
    out.iterations += CeresIterations(summary);
    out.final_cost = CeresCost(summary.final_cost);
    out.solve_time_s += summary.total_time_in_seconds;
    out.preprocessor_time_s += summary.preprocessor_time_in_seconds;
    out.evaluation_time_s +=
        summary.residual_evaluation_time_in_seconds + summary.jacobian_evaluation_time_in_seconds;
    out.linear_solver_time_s += summary.linear_solver_time_in_seconds;
    out.num_residuals = summary.num_residuals;
    out.num_free_parameters = summary.num_effective_parameters_reduced;
    if (options_.full_report) out.full_report += summary.FullReport();
    out.termination = ceres::TerminationTypeToString(summary.termination_type);
    out.message = summary.message;
  };

  // Starting values, to solve again with pi held if the step cannot observe it.
  const std::array<double, kPlaneSize> plane_before = plane_;
  std::vector<std::array<double, kPoseSize>> poses_before;
  for (int id : free_ids) poses_before.push_back(frames_.at(id).pose);

  solve(/*first=*/true);
  // The motion gate (motion_gate.h), in rounds, each followed by a solve, before the plane
  // gate; for this step only (a redo, after the caller's tracker gate, judges again).
  // (a failed solve, e.g. an evaluation failing at the starting point, is left to the caller:
  // neither gate judges a problem that cannot be evaluated)
  const auto failed = [&out] { return out.termination == "FAILURE"; };
  int releases_left =
      failed() ? 0 : MaxMotionReleases(static_cast<int>(motion.blocks.size()), c.motion_gate_chi2);
  while (releases_left > 0) {
    const std::vector<int> released =
        ReleaseMotionBlocks(&problem, &motion, c.motion_gate_chi2, releases_left);
    if (released.empty()) break;
    releases_left -= static_cast<int>(released.size());
    out.motion_released_ids.insert(out.motion_released_ids.end(), released.begin(),
                                   released.end());
    solve(/*first=*/false);
  }
  // (the limit is stated for sigma_v = 1 px: see SlidingWindowOptions::plane_max_relative_std)
  const double limit = options_.plane_max_relative_std * c.sigma_v_px;
  if (plane_free && limit > 0.0 && !failed()) {
    std::vector<double*> free_poses;
    for (int id : free_ids) free_poses.push_back(frames_.at(id).pose.data());
    out.plane_relative_std =
        PlaneRelativeStd(&problem, plane_.data(), free_poses, plane_norm_before);
    if (!(out.plane_relative_std <= limit)) {
      // Same residual blocks, pi constant at its value before the step: the problem points at
      // plane_ and the poses, so restoring them restarts the solve from the same values.
      plane_ = plane_before;
      for (size_t i = 0; i < free_ids.size(); ++i) frames_.at(free_ids[i]).pose = poses_before[i];
      problem.SetParameterBlockConstant(plane_.data());
      out.plane_held = true;
      solve(/*first=*/false);
    }
  }
  auto term_cost = [&problem](const std::vector<ceres::ResidualBlockId>& ids) {
    if (ids.empty()) return 0.0;
    ceres::Problem::EvaluateOptions eo;
    eo.residual_blocks = ids;
    double cost = 0.0;
    // A failed evaluation (a camera on the plane) is no cost of 0.
    if (!problem.Evaluate(eo, &cost, nullptr, nullptr, nullptr)) {
      return std::numeric_limits<double>::quiet_NaN();
    }
    return cost;
  };
  out.visual_cost = term_cost(visual_blocks);
  out.emt_cost = term_cost(emt_blocks);
  out.motion_cost = term_cost(motion.blocks);
  return out;
}

void SlidingWindow::Forget(const std::vector<int>& frame_ids) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<int> pending;
  for (const auto& [id, f] : frames_)
    if (!f.fixed) pending.push_back(id);
  const std::vector<int> window = WindowIdsLocked(std::max<int>(1, pending.size()));
  // The two cameras before the first pending frame: its C_p (Eq. 27) and, without a tracker
  // sample, its starting pose (Eq. 16) take them. The window holds them while at most
  // window_size - 2 frames are pending; with more it holds fewer (none from window_size on),
  // and an older camera would silently stand in for a forgotten one.
  std::vector<int> predecessors;
  if (!pending.empty()) {
    for (auto it = frames_.find(pending.front());
         it != frames_.begin() && predecessors.size() < 2;) {
      predecessors.push_back((--it)->first);
    }
  }
  // Every id checked before any is dropped: a refused call changes nothing.
  for (int id : frame_ids) {
    auto it = frames_.find(id);
    if (it == frames_.end()) continue;
    if (!it->second.fixed || std::count(window.begin(), window.end(), id)) {
      throw std::invalid_argument("forget: frame " + std::to_string(id) +
                                  " is pending or in the window");
    }
    if (std::count(predecessors.begin(), predecessors.end(), id)) {
      throw std::invalid_argument(
          "forget: frame " + std::to_string(id) + " is one of the two cameras before the first "
          "pending frame " + std::to_string(pending.front()) + ", which its constant-velocity "
          "prior links it to (the window keeps them only while at most window_size - 2 = " +
          std::to_string(options_.window_size - 2) + " frames are pending; " +
          std::to_string(pending.size()) + " are)");
    }
  }
  for (int id : frame_ids) {
    auto it = frames_.find(id);
    if (it == frames_.end()) continue;  // (unknown, or listed twice)
    for (const auto& key : it->second.pair_keys) {
      auto p = pairs_.find(key);
      if (p == pairs_.end()) continue;
      num_correspondences_ -= static_cast<int>(p->second.points_l.cols());
      const int other = key.first == id ? key.second : key.first;
      auto o = frames_.find(other);
      if (o != frames_.end()) {
        auto& keys = o->second.pair_keys;
        keys.erase(std::remove(keys.begin(), keys.end(), key), keys.end());
      }
      pairs_.erase(p);
    }
    frames_.erase(it);
  }
}

SlidingWindow::Pose SlidingWindow::GetPose(int frame_id) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const Frame& f = FindFrame(frame_id, "pose");
  // A pending frame added without an initial pose has none until its step (zeros, not a pose);
  // a fixed one whose tracker sample was dropped keeps its last estimate until a Redo.
  if (!f.fixed && !f.has_initial) {
    throw std::invalid_argument("pose: frame " + std::to_string(frame_id) +
                                " is pending without a pose yet (no initial pose; its step "
                                "gives it one)");
  }
  return ToVector(f.pose);
}

Eigen::Vector3d SlidingWindow::Plane() const {
  std::lock_guard<std::mutex> lock(mutex_);
  if (!plane_set_) throw std::invalid_argument("plane: not set (call set_plane first)");
  return Eigen::Map<const Eigen::Vector3d>(plane_.data());
}

std::vector<int> SlidingWindow::PendingIds() const {
  std::lock_guard<std::mutex> lock(mutex_);
  std::vector<int> out;
  for (const auto& [id, f] : frames_)
    if (!f.fixed) out.push_back(id);
  return out;
}

std::vector<int> SlidingWindow::WindowIds() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return WindowIdsLocked(options_.num_new);
}

int SlidingWindow::NumFrames() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(frames_.size());
}

int SlidingWindow::NumPairs() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return static_cast<int>(pairs_.size());
}

int SlidingWindow::NumCorrespondences() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return num_correspondences_;
}

}  // namespace fusedmosaic
