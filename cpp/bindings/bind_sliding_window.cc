// Python bindings of cpp/fusedmosaic/problem/sliding_window.h (LBAVis+EMT).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "bindings/bind.h"
#include "fusedmosaic/problem/sliding_window.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

std::optional<Vector6d> OptionalPose(const std::optional<DoubleArray>& v, const char* name) {
  if (!v) return std::nullopt;
  return Vector6d(ToVector(*v, kPoseSize, name));
}

SlidingWindow::Points Points(const DoubleArray& p, const char* name) {
  return ToMatrix(p, -1, 2, name);
}

}  // namespace

void BindSlidingWindow(py::module_& m) {
  py::class_<SlidingWindowOptions>(m, "SlidingWindowOptions",
                                   "Options of the LBA sliding window (seed 000, Sec. 4.2).")
      .def(py::init([](int window_size, int num_new,
                       const std::optional<BundleAdjusterOptions>& costs) {
             SlidingWindowOptions o;
             o.window_size = window_size;
             o.num_new = num_new;
             if (costs) o.costs = *costs;
             o.Validate();
             return o;
           }),
           "window_size"_a = 5, "num_new"_a = 3, "costs"_a = py::none(),
           "window_size: W; num_new: chi_e; costs: BundleAdjusterOptions (weights, loss, solver)")
      .def_readwrite("window_size", &SlidingWindowOptions::window_size)
      .def_readwrite("num_new", &SlidingWindowOptions::num_new)
      .def_readwrite("costs", &SlidingWindowOptions::costs)
      .def_readwrite("fold_fixed_cameras", &SlidingWindowOptions::fold_fixed_cameras,
                     "C_v blocks take the poses of the step's fixed cameras as values, so\n"
                     "their Jacobians span the free parameters only (same residuals)")
      .def_readwrite("full_report", &SlidingWindowOptions::full_report,
                     "keep Ceres' FullReport() in each step summary (diagnostics)")
      .def_readwrite("plane_max_relative_std", &SlidingWindowOptions::plane_max_relative_std,
                     "plane observability gate: a step whose costs give pi a relative std\n"
                     "sqrt(trace(Cov_pi)) / |pi| above this is solved again with pi held\n"
                     "(0: gate and std computation off, plane_relative_std NaN)")
      // Pickled (copy, deepcopy, multiprocessing) as the tuple of its fields.
      .def(py::pickle(
          [](const SlidingWindowOptions& o) {
            return py::make_tuple(o.window_size, o.num_new, o.costs, o.fold_fixed_cameras,
                                  o.full_report, o.plane_max_relative_std);
          },
          [](const py::tuple& t) {
            if (t.size() != 6) {
              throw std::runtime_error("SlidingWindowOptions: pickled state of " +
                                       std::to_string(t.size()) + " fields, expected 6");
            }
            SlidingWindowOptions o;
            o.window_size = t[0].cast<int>();
            o.num_new = t[1].cast<int>();
            o.costs = t[2].cast<BundleAdjusterOptions>();
            o.fold_fixed_cameras = t[3].cast<bool>();
            o.full_report = t[4].cast<bool>();
            o.plane_max_relative_std = t[5].cast<double>();
            return o;
          }));

  py::class_<WindowStepSummary>(m, "WindowStepSummary", "Result of SlidingWindow.step() / redo().")
      .def_readonly("frame_ids", &WindowStepSummary::frame_ids)
      .def_readonly("fixed_ids", &WindowStepSummary::fixed_ids)
      .def_readonly("keyframe_ids", &WindowStepSummary::keyframe_ids)
      .def_readonly("emt_mahalanobis2", &WindowStepSummary::emt_mahalanobis2)
      .def_readonly("iterations", &WindowStepSummary::iterations,
                    "Ceres iterations as SolveSummary's, summed over the step's runs (motion\n"
                    "gate rounds, the plane gate's second solve)")
      .def_readonly("initial_cost", &WindowStepSummary::initial_cost)
      .def_readonly("final_cost", &WindowStepSummary::final_cost)
      .def_readonly("visual_cost", &WindowStepSummary::visual_cost)
      .def_readonly("emt_cost", &WindowStepSummary::emt_cost)
      .def_readonly("motion_cost", &WindowStepSummary::motion_cost)
      .def_readonly("solve_time_s", &WindowStepSummary::solve_time_s)
      .def_readonly("step_time_s", &WindowStepSummary::step_time_s)
      .def_readonly("termination", &WindowStepSummary::termination)
      .def_readonly("message", &WindowStepSummary::message,
                    "Ceres' summary message of the step's last solve (why it stopped, e.g. a\n"
                    "FAILURE's \"Residual and Jacobian evaluation failed.\"); empty without a\n"
                    "solve (NO_RESIDUALS)")
      .def_readonly("num_visual_blocks", &WindowStepSummary::num_visual_blocks)
      .def_readonly("num_correspondences", &WindowStepSummary::num_correspondences)
      .def_readonly("num_window_correspondences", &WindowStepSummary::num_window_correspondences)
      .def_readonly("num_keyframe_correspondences",
                    &WindowStepSummary::num_keyframe_correspondences)
      .def_readonly("num_loop_correspondences", &WindowStepSummary::num_loop_correspondences)
      .def_readonly("num_temporal_correspondences",
                    &WindowStepSummary::num_temporal_correspondences,
                    "correspondences of pairs with one of the window_size - 1 frames before the "
                    "first new one, outside the window (the new frames' temporal pairs)")
      .def_readonly("num_fixed_pair_correspondences",
                    &WindowStepSummary::num_fixed_pair_correspondences,
                    "correspondences of pairs of two fixed cameras (they constrain pi only)")
      .def_readonly("num_residuals", &WindowStepSummary::num_residuals)
      .def_readonly("num_free_parameters", &WindowStepSummary::num_free_parameters)
      .def_readonly("plane_relative_std", &WindowStepSummary::plane_relative_std,
                    "sqrt(trace(Cov_pi)) / |pi before the step| from the step's costs (NaN:\n"
                    "no visual cost or gate off; inf: pi unobservable; a held step: its\n"
                    "first solve's)")
      .def_readonly("plane_held", &WindowStepSummary::plane_held,
                    "pi kept its value from before the step (no visual cost, or the gate)")
      .def_readonly("motion_released_ids", &WindowStepSummary::motion_released_ids,
                    "estimated cameras whose C_p block the motion gate released in this step")
      .def_readonly("preprocessor_time_s", &WindowStepSummary::preprocessor_time_s)
      .def_readonly("evaluation_time_s", &WindowStepSummary::evaluation_time_s,
                    "Ceres residual + Jacobian evaluation time")
      .def_readonly("linear_solver_time_s", &WindowStepSummary::linear_solver_time_s)
      .def_readonly("full_report", &WindowStepSummary::full_report,
                    "Ceres' FullReport() when SlidingWindowOptions.full_report, else empty");

  py::class_<SlidingWindow>(
      m, "SlidingWindow",
      "Local bundle adjustment over a sliding window with keyframes (LBAVis+EMT, Eqs. 24-27).\n"
      "Frames are added in increasing id order; step() estimates the pending ones and the plane\n"
      "with the window and the given keyframes fixed, then fixes them. Calls from other threads\n"
      "wait while step() or redo() runs (with the GIL released: only the caller waits).")
      .def(py::init([](const DoubleArray& camera_matrix, const SlidingWindowOptions& options) {
             return std::make_unique<SlidingWindow>(
                 Eigen::Matrix3d(ToMatrix(camera_matrix, 3, 3, "camera_matrix")), options);
           }),
           "camera_matrix"_a, "options"_a = SlidingWindowOptions())
      .def(
          "add_frame",
          [](SlidingWindow& self, int frame_id, const std::optional<DoubleArray>& initial,
             const std::optional<DoubleArray>& emt_measurement, bool fixed,
             double motion_ratio, double motion_sigma_scale) {
            const std::optional<Vector6d> x = OptionalPose(initial, "initial");
            const std::optional<Vector6d> z = OptionalPose(emt_measurement, "emt_measurement");
            py::gil_scoped_release release;
            self.AddFrame(frame_id, x, z, fixed, motion_ratio, motion_sigma_scale);
          },
          "frame_id"_a, "initial"_a = py::none(), "emt_measurement"_a = py::none(),
          "fixed"_a = false, "motion_ratio"_a = 1.0, "motion_sigma_scale"_a = 1.0,
          "initial, emt_measurement : (6,) float64 cam_from_world [r, t] or None\n"
          "fixed : already estimated (enters the window fixed; needs initial)\n"
          "The window's first frame needs initial or emt_measurement (ValueError otherwise).\n"
          "motion_ratio, motion_sigma_scale : timing of the constant-velocity prior linking this\n"
          "    camera to the two preceding ones (1, 1: evenly spaced; 0, inf: no prior across a\n"
          "    long gap, the camera starting at the preceding one; see BundleAdjuster)")
      .def("set_emt_sigma_scale", &SlidingWindow::SetEmtSigmaScale, "frame_id"_a, "scale"_a,
           py::call_guard<py::gil_scoped_release>())
      .def("set_sigma_v", &SlidingWindow::SetSigmaV, "sigma_v_px"_a,
           py::call_guard<py::gil_scoped_release>(),
           "The visual cost's sigma_v (px, finite, > 0) from the next step or redo on (every\n"
           "pair held is weighed by it then).")
      .def_property_readonly("sigma_v_px", Released(&SlidingWindow::sigma_v_px))
      .def("drop_emt_measurement", &SlidingWindow::DropEmtMeasurement, "frame_id"_a,
           py::call_guard<py::gil_scoped_release>(),
           "Drops a frame's tracker measurement (an unusable sample, e.g. one putting the camera\n"
           "centre on the plane): no C_EMT term, and its pose is initialised again from the\n"
           "constant-velocity prediction by the next step or redo that estimates it.\n"
           "ValueError for the window's first frame while pending (no predecessors).")
      .def("set_motion_timing", &SlidingWindow::SetMotionTiming, "frame_id"_a,
           "motion_ratio"_a, "motion_sigma_scale"_a, py::call_guard<py::gil_scoped_release>(),
           "The timing of a frame's constant-velocity prior (as add_frame's), from the next "
           "step or redo that estimates it on.")
      .def(
          "add_pair",
          [](SlidingWindow& self, int frame_l, int frame_m, const DoubleArray& points_l,
             const DoubleArray& points_m) {
            const SlidingWindow::Points pl = Points(points_l, "points_l");
            const SlidingWindow::Points pm = Points(points_m, "points_m");
            py::gil_scoped_release release;
            self.AddPair(frame_l, frame_m, pl, pm);
          },
          "frame_l"_a, "frame_m"_a, "points_l"_a, "points_m"_a,
          "points_l, points_m : (N, 2) float64 pixels; transfer m -> l")
      .def(
          "set_plane",
          [](SlidingWindow& self, const DoubleArray& plane) {
            const Eigen::Vector3d pi = ToPlane(plane);
            py::gil_scoped_release release;
            self.SetPlane(pi);
          },
          "plane"_a)
      .def("step", &SlidingWindow::Step, "keyframe_ids"_a = std::vector<int>{},
           "hold_plane"_a = false, py::call_guard<py::gil_scoped_release>(),
           "Estimates the pending frames and the plane (GIL released); hold_plane: pi kept.")
      .def("redo", &SlidingWindow::Redo, "frame_ids"_a, "keyframe_ids"_a = std::vector<int>{},
           "hold_plane"_a = false, py::call_guard<py::gil_scoped_release>(),
           "Re-estimates the last frames (GIL released), e.g. after gating a tracker sample,\n"
           "each started again as a step starts it: from its tracker sample, or the constant-\n"
           "velocity prediction without one or when the sample is gated (sigma scale > 1; a\n"
           "frame add_frame gave an initial pose but no sample: the prediction too);\n"
           "frame_ids, distinct, must hold every frame from the first of them on (the last\n"
           "step's, and any added since), with no pending frame before them, the window's\n"
           "first frame among them only with a tracker sample; keyframe_ids fixed frames not\n"
           "among them. ValueError (IndexError: an unknown id) else, with nothing changed.")
      .def("forget", &SlidingWindow::Forget, "frame_ids"_a,
           py::call_guard<py::gil_scoped_release>(),
           "Drops fixed frames outside the window and their pairs (unknown ids ignored).\n"
           "ValueError, nothing dropped, for a pending frame, one in the window, or one of the\n"
           "two frames before the first pending one (its constant-velocity prior's).")
      .def("pose", &SlidingWindow::GetPose, "frame_id"_a,
           py::call_guard<py::gil_scoped_release>(),
           "(6,) cam_from_world; ValueError for a pending frame without a pose yet (no\n"
           "initial pose: it gets one at its step).")
      .def("plane", &SlidingWindow::Plane, py::call_guard<py::gil_scoped_release>(),
           "(3,) pi = n / d; ValueError before set_plane.")
      .def("pending_ids", &SlidingWindow::PendingIds, py::call_guard<py::gil_scoped_release>())
      .def("window_ids", &SlidingWindow::WindowIds, py::call_guard<py::gil_scoped_release>())
      .def_property_readonly("num_frames", Released(&SlidingWindow::NumFrames))
      .def_property_readonly("num_pairs", Released(&SlidingWindow::NumPairs))
      .def_property_readonly("num_correspondences", Released(&SlidingWindow::NumCorrespondences));
}

}  // namespace fusedmosaic::bindings
