// Local Bundle Adjustment over a sliding window: LBAVis+EMT (seed 000, Sec. 3.4, Eqs. 21-27).
//
// Each step estimates the chi_e pending (new) cameras X_e and the plane pi, with
//   * the previous W - chi_e estimated cameras X_g held fixed (the temporal window),
//   * sparse keyframe sets chosen by the caller (fixed cameras whose correspondences keep pi
//     well observed across the explored area, Fig. 5),
// minimising                 C_v + C_EMT + C_p                                       (Eq. 24)
//   C_v   visual transfer over every stored pair whose two frames are in the step (Eq. 25);
//         fixed cameras that share a stored pair with a new camera join the step as constants
//         (the caller's spatial loop pairs, the paper's suggested spatio-temporal window);
//   C_EMT tracker prior on the new cameras (Eq. 26);
//   C_p   constant velocity for each new camera from its two predecessors in the sequence,
//         new or fixed, which includes the two terms linking x_1^e and x_2^e to the last
//         fixed cameras x_{chi_g}^g, x_{chi_g - 1}^g (Eq. 27).
// After the step the new cameras are fixed for good (assumption (ii) of Sec. 3.4); pi stays free
// in later steps. Frames are ordered by id (ids must increase), which is the sequence order.
//
// Memory: poses, tracker measurements and correspondences of frames the caller has not
// Forget()-ed. The caller (python/fusedmosaic/estimation/sequential.py) forgets what neither the
// window nor keyframe selection can use, so the state stays bounded.
#pragma once

#include <Eigen/Core>
#include <array>
#include <limits>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "fusedmosaic/problem/bundle_adjuster.h"

namespace fusedmosaic {

struct SlidingWindowOptions {
  int window_size = 5;  // W, cameras in the temporal window (paper Sec. 4.2, SYN preset)
  int num_new = 3;      // chi_e, new cameras estimated per step (SYN preset)
  // With costs.use_motion_prior, window_size - num_new >= 2: C_p links the first new camera to
  // its two predecessors, which only the window keeps from Forget (Validate refuses less).
  // Cost weights, robust loss and Ceres settings shared with the bundle adjuster; use_emt and
  // use_motion_prior switch C_EMT and C_p. costs.linear_solver "auto" is sparse_normal_cholesky
  // for the window (measured, see sliding_window.cc); the iteration limit, tolerances and thread
  // count are set by the caller (estimation/sequential.py).
  BundleAdjusterOptions costs;
  // C_v blocks of pairs with a camera held constant in the step take its pose as a value, so
  // their Jacobians span the free parameters only (9 or 3 columns instead of 15); the residuals
  // are the same. false: every block has both poses as (constant) parameters.
  // bench/bench_sequential.py: median step 5.6 -> 3.0 ms (sparse_normal_cholesky), 8.6 -> 5.8 ms
  // (dense_normal_cholesky); identical poses and plane.
  bool fold_fixed_cameras = true;
  bool full_report = false;  // keep Ceres' FullReport() in each step summary (diagnostics)
  // Plane observability gate (not in the paper). After each step the marginal covariance of pi
  // given the step's costs is computed from the Jacobian at the solution; its relative standard
  // deviation sqrt(trace(Cov_pi)) / |pi| combines the relative error of the plane distance and
  // the tilt error of its normal (rad). Above this value the step cannot tell where the plane
  // is (e.g. its only visual evidence is one pair between cameras the tracker placed: pi then
  // absorbs tracker noise and can run off to infinity), so the step is solved again with pi held
  // at its value before the step. Measured in normal operation (SYN, hand-held, with and
  // without black frames): 0.0004 to 0.0104. 0 disables the gate and its cost (one more
  // Jacobian evaluation per step, ~0.6 ms on SYN); plane_relative_std is then NaN.
  // The value is for costs.sigma_v_px = 1 px (the paper's, with which it was measured); the
  // step compares with it x sigma_v_px / 1 px: pi is observed through C_v alone, so its std
  // scales with sigma_v. On the weak-texture scene with sigma_v 0.085 px (measured by the
  // start-up), 0.02 held 3 steps (a frame 54 px off, the tracker alone 35 px), 0.02 x 0.085 the
  // 37 that 0.02 holds at 1 px (27 px).
  double plane_max_relative_std = 0.02;

  void Validate() const;
};

struct WindowStepSummary {
  std::vector<int> frame_ids;  // the cameras estimated (and now fixed)
  std::vector<int> fixed_ids;  // the window cameras held fixed
  std::vector<int> keyframe_ids;
  // Per estimated camera: (x - z)^T Sigma_EMT^-1 (x - z) at the solution with the nominal
  // Sigma_EMT, x - z as C_EMT takes it (pose_prior.h), NaN without a measurement. Used by the caller to gate gross tracker outliers.
  std::vector<double> emt_mahalanobis2;
  int iterations = 0;  // Ceres iterations (CeresIterations), summed over the step's runs
  // Costs as SolveSummary's: NaN where they could not be evaluated (a FAILURE termination).
  double initial_cost = 0.0;
  double final_cost = 0.0;
  double visual_cost = 0.0;
  double emt_cost = 0.0;
  double motion_cost = 0.0;
  double solve_time_s = 0.0;  // Ceres' total time
  double step_time_s = 0.0;   // assembly + solve
  std::string termination;
  // Ceres' Summary::message of the step's last solve (why it stopped; on a FAILURE, e.g.
  // "Residual and Jacobian evaluation failed."), empty without a solve (NO_RESIDUALS).
  std::string message;
  int num_visual_blocks = 0;
  int num_correspondences = 0;
  // Correspondences of C_v by the role of the pair's cameras: a pair touching a keyframe
  // counts as keyframe, else one touching a loop camera (a fixed camera outside the window
  // paired with a new one, not temporal) as loop, else one touching a temporal camera (one of
  // the window_size - 1 frames before the first new one, outside the window: the predecessors
  // a caller matches each new frame with, as SequentialMosaicker does) as temporal, else window
  // (new and window cameras).
  int num_window_correspondences = 0;
  int num_keyframe_correspondences = 0;
  int num_loop_correspondences = 0;
  int num_temporal_correspondences = 0;
  int num_fixed_pair_correspondences = 0;  // pairs of two fixed cameras: they only see pi
  int num_residuals = 0;
  int num_free_parameters = 0;
  // Plane observability (SlidingWindowOptions::plane_max_relative_std): the relative standard
  // deviation of pi from this step's costs, relative to |pi| before the step (NaN when pi had no
  // visual cost in the step or the gate is disabled; inf when pi is not observable: J^T J
  // singular in a direction that moves pi; for a step the gate held, the value of its first
  // solve), and whether pi kept its value from before the step. The times and iterations of a
  // held step cover both solves.
  double plane_relative_std = std::numeric_limits<double>::quiet_NaN();
  bool plane_held = false;
  // Estimated cameras whose C_p block the motion gate released in this step or redo
  // (costs.motion_gate_chi2), in order. Iterations and times cover every round.
  std::vector<int> motion_released_ids;
  // Ceres' time split (s): building the reduced problem, residual + Jacobian evaluation, linear
  // solves; and Ceres' FullReport() (empty unless SlidingWindowOptions::full_report).
  double preprocessor_time_s = 0.0;
  double evaluation_time_s = 0.0;
  double linear_solver_time_s = 0.0;
  std::string full_report;
};

class SlidingWindow {
 public:
  using Pose = Vector6d;
  using Points = Eigen::Matrix<double, Eigen::Dynamic, 2>;

  explicit SlidingWindow(const Eigen::Matrix3d& camera_matrix,
                         const SlidingWindowOptions& options = SlidingWindowOptions());
  SlidingWindow(const SlidingWindow&) = delete;
  SlidingWindow& operator=(const SlidingWindow&) = delete;

  // Adds a pending camera. frame_id must exceed every id added so far. initial: starting pose
  // (cam_from_world); when absent the step starts from the tracker measurement, or else from
  // the constant-velocity prediction of the two preceding cameras. fixed: the camera is already
  // estimated (e.g. by the bootstrap bundle adjustment) and enters the window as such; it then
  // needs `initial`. The window's first frame needs `initial` or `emt_measurement`: it has no
  // predecessors to be predicted from (std::invalid_argument otherwise).
  // motion_ratio, motion_sigma_scale: timing of the constant-velocity prior linking this camera
  // to the two preceding ones (see BundleAdjuster::AddFrame); 1, 1 for evenly spaced frames.
  void AddFrame(int frame_id, const std::optional<Pose>& initial,
                const std::optional<Pose>& emt_measurement, bool fixed = false,
                double motion_ratio = 1.0, double motion_sigma_scale = 1.0);
  // Inflates the tracker standard deviations of a pending camera (gating, >= 1).
  void SetEmtSigmaScale(int frame_id, double scale);
  // The visual cost's sigma_v (pixels, finite, > 0) from the next Step or Redo on: the caller
  // measured the keypoints' noise (e.g. the start-up's transfer residuals). The C_v blocks are
  // built at each step from costs, so every pair, held or new, is weighed by it from then on.
  void SetSigmaV(double sigma_v_px);
  double sigma_v_px() const;
  // Drops a camera's tracker measurement (a sample the caller found unusable, e.g. one that
  // puts the camera centre on the plane, so that the step's evaluation failed): no C_EMT term
  // for it any more, its sigma scale back to 1, and its pose is initialised again, from the
  // constant-velocity prediction of its predecessors, by the next Step or Redo that estimates
  // it (until then a pending camera has no pose: GetPose refuses it; a fixed one keeps its last
  // estimate, which later steps hold constant, until a Redo estimates it again). Refused
  // (std::invalid_argument) for the window's first frame while pending: it has no predecessors.
  void DropEmtMeasurement(int frame_id);
  // The timing of a camera's constant-velocity prior, as AddFrame's, from the next Step or
  // Redo that estimates it on (e.g. judged again when later tracker samples are known).
  void SetMotionTiming(int frame_id, double motion_ratio, double motion_sigma_scale);
  void AddPair(int frame_l, int frame_m, const Points& points_l, const Points& points_m);
  void SetPlane(const Eigen::Vector3d& plane);

  // Estimates all pending cameras (1 <= count) and the plane; keyframe_ids must be fixed cameras.
  // hold_plane: pi kept at its value (the caller knows the step cannot inform it, e.g. cameras
  // with neither a tracker sample nor a visual link to an anchored camera).
  WindowStepSummary Step(const std::vector<int>& keyframe_ids, bool hold_plane = false);
  // Re-runs the last step's problem after SetEmtSigmaScale (gating) and refixes its cameras,
  // each started again as Step starts it: at its tracker sample, or at the constant-velocity
  // prediction when it has none or its sample is gated (sigma scale > 1), also when AddFrame
  // gave it an initial pose (not kept); the plane where it is.
  // frame_ids must be distinct and hold every frame from the first of them on (the last step's
  // cameras, and any added since), with no pending frame before them, and the window's first
  // frame among them needs a tracker sample (no predecessors): std::invalid_argument otherwise
  // (std::out_of_range for an unknown id), with nothing changed.
  WindowStepSummary Redo(const std::vector<int>& frame_ids, const std::vector<int>& keyframe_ids,
                         bool hold_plane = false);

  // Drops fixed cameras outside the current window, with their pairs; unknown ids are ignored.
  // Refuses (std::invalid_argument, nothing dropped) a pending camera, one in the window, and
  // the two cameras before the first pending one (its C_p links it to them, Eq. 27), which
  // the window no longer holds when more than window_size - 2 cameras are pending.
  void Forget(const std::vector<int>& frame_ids);

  // Throw std::invalid_argument for a pending camera added without an initial pose (it has none
  // until its step) and before SetPlane.
  Pose GetPose(int frame_id) const;
  Eigen::Vector3d Plane() const;
  std::vector<int> PendingIds() const;
  std::vector<int> WindowIds() const;  // fixed cameras the next step would hold in its window
  int NumFrames() const;
  int NumPairs() const;
  int NumCorrespondences() const;
  const SlidingWindowOptions& options() const { return options_; }

 private:
  struct Frame {
    std::array<double, kPoseSize> pose{};
    bool has_initial = false;
    std::optional<Pose> emt_measurement;
    double emt_sigma_scale = 1.0;
    bool fixed = false;
    double motion_ratio = 1.0;
    double motion_sigma_scale = 1.0;
    std::vector<std::pair<int, int>> pair_keys;  // keys into pairs_
  };
  struct Pair {
    Eigen::Matrix<double, 2, Eigen::Dynamic> points_l;
    Eigen::Matrix<double, 2, Eigen::Dynamic> points_m;
  };

  Frame& FindFrame(int frame_id, const char* what);
  // Refuses (out_of_range / invalid_argument) a keyframe id that is unknown, not fixed, or
  // among the frames the call estimates, before anything changes.
  void CheckKeyframes(const std::vector<int>& keyframe_ids, const std::vector<int>& free_ids,
                      const char* what) const;
  const Frame& FindFrame(int frame_id, const char* what) const;
  std::vector<int> WindowIdsLocked(int num_new) const;
  void InitialisePending(const std::vector<int>& ids);
  WindowStepSummary Solve(std::vector<int> free_ids, const std::vector<int>& keyframe_ids,
                          bool hold_plane);
  WindowStepSummary SolveStep(const std::vector<int>& free_ids,
                              const std::vector<int>& keyframe_ids, bool hold_plane);

  mutable std::mutex mutex_;
  Eigen::Matrix3d camera_matrix_;
  SlidingWindowOptions options_;
  std::map<int, Frame> frames_;                // ordered by id = sequence order
  std::map<std::pair<int, int>, Pair> pairs_;  // (frame_l, frame_m)
  std::array<double, kPlaneSize> plane_{};
  bool plane_set_ = false;
  int num_correspondences_ = 0;
};

}  // namespace fusedmosaic
