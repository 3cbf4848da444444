// Python bindings of cpp/fusedmosaic/problem: BundleAdjuster, its options and solve summary.
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "bindings/bind.h"
#include "fusedmosaic/problem/bundle_adjuster.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

Vector6d ToPose(const DoubleArray& v, const char* name) { return ToVector(v, kPoseSize, name); }

BundleAdjuster::Points ToPoints(const DoubleArray& points, const char* name) {
  return ToMatrix(points, -1, 2, name);
}

// Field names of BundleAdjusterOptions, in declaration order (repr and keyword construction).
constexpr const char* kOptionFields[] = {"sigma_v_px",
                                         "emt_sigma",
                                         "motion_sigma",
                                         "loss",
                                         "loss_scale_px",
                                         "linear_solver",
                                         "trust_region",
                                         "residual_blocks",
                                         "condense_pairs",
                                         "max_iterations",
                                         "function_tolerance",
                                         "gradient_tolerance",
                                         "parameter_tolerance",
                                         "num_threads",
                                         "use_emt",
                                         "use_motion_prior",
                                         "motion_gate_chi2",
                                         "plane_std",
                                         "plane_std_paired_only"};

constexpr const char* kSummaryFields[] = {"iterations",
                                          "initial_cost",
                                          "final_cost",
                                          "visual_cost",
                                          "emt_cost",
                                          "motion_cost",
                                          "solve_time_s",
                                          "termination",
                                          "message",
                                          "linear_solver",
                                          "num_residual_blocks",
                                          "num_residuals",
                                          "num_parameters",
                                          "num_free_parameters",
                                          "num_visual_blocks",
                                          "num_emt_blocks",
                                          "num_motion_blocks",
                                          "gauge_fixed_by_constraints",
                                          "plane_relative_std",
                                          "plane_std_time_s",
                                          "motion_released_ids"};

// BundleAdjusterOptions from {field: value}: keyword construction and unpickling.
BundleAdjusterOptions OptionsFromDict(const py::dict& fields) {
  BundleAdjusterOptions options;
  py::object self = py::cast(options);
  for (const auto& item : fields) {
    const std::string key = py::str(item.first);
    bool known = false;
    for (const char* field : kOptionFields) known = known || key == field;
    if (!known) {
      throw py::type_error("BundleAdjusterOptions: unknown option '" + key + "'");
    }
    self.attr(key.c_str()) = item.second;
  }
  return self.cast<BundleAdjusterOptions>();
}

std::string Repr(const py::object& self, const char* cls, const char* const* fields, size_t n) {
  std::ostringstream out;
  out << cls << "(";
  for (size_t i = 0; i < n; ++i) {
    out << (i ? ", " : "") << fields[i] << "="
        << py::repr(self.attr(fields[i])).cast<std::string>();
  }
  out << ")";
  return out.str();
}

}  // namespace

void BindProblem(py::module_& m) {
  py::class_<BundleAdjusterOptions>(m, "BundleAdjusterOptions",
                                    "Options of BundleAdjuster; defaults from seed 000 "
                                    "(Sec. 4.2, appendix Eq. 30). Keyword construction: "
                                    "BundleAdjusterOptions(loss='huber', ...).")
      .def(py::init([](const py::kwargs& kwargs) { return OptionsFromDict(kwargs); }))
      // Pickled (copy, deepcopy, multiprocessing) as the dict of its fields.
      .def(py::pickle(
          [](const py::object& self) {
            py::dict state;
            for (const char* field : kOptionFields) state[field] = self.attr(field);
            return state;
          },
          [](const py::dict& state) { return OptionsFromDict(state); }))
      .def_readwrite("sigma_v_px", &BundleAdjusterOptions::sigma_v_px,
                     "sigma_v, pixels (paper Sec. 4.2: 1 px).")
      .def_property(
          "emt_sigma", [](const BundleAdjusterOptions& o) { return Eigen::VectorXd(o.emt_sigma); },
          [](BundleAdjusterOptions& o, const DoubleArray& v) {
            o.emt_sigma = ToPose(v, "emt_sigma");
          },
          "(6,) float64 EMT prior standard deviations [rad x3, mm x3] (appendix Eq. 30). "
          "Returns a copy: assign the whole array.")
      .def_property(
          "motion_sigma",
          [](const BundleAdjusterOptions& o) { return Eigen::VectorXd(o.motion_sigma); },
          [](BundleAdjusterOptions& o, const DoubleArray& v) {
            o.motion_sigma = ToPose(v, "motion_sigma");
          },
          "(6,) float64 constant-velocity prior standard deviations [rad x3, mm x3] "
          "(appendix Eq. 30). Returns a copy: assign the whole array.")
      .def_readwrite("loss", &BundleAdjusterOptions::loss,
                     "'none' | 'huber' | 'cauchy', applied per correspondence.")
      .def_readwrite("loss_scale_px", &BundleAdjusterOptions::loss_scale_px,
                     "Robust kernel scale, pixels.")
      .def_readwrite("linear_solver", &BundleAdjusterOptions::linear_solver,
                     "'auto' (sparse_schur, measured fastest in bench/bench_solvers.py), "
                     "'dense_schur', 'sparse_schur', 'sparse_normal_cholesky', 'dense_qr', "
                     "'dense_normal_cholesky' or 'iterative_schur'.")
      .def_readwrite("trust_region", &BundleAdjusterOptions::trust_region,
                     "'levenberg_marquardt' (default) or 'dogleg' (Ceres' trust region\n"
                     "strategy; dogleg takes Gauss-Newton steps where they fit, see\n"
                     "SequentialOptions.startup_trust_region).")
      .def_readwrite("residual_blocks", &BundleAdjusterOptions::residual_blocks,
                     "'per_pair' (default) or 'per_point' residual blocks.")
      .def_readwrite("condense_pairs", &BundleAdjusterOptions::condense_pairs,
                     "Per-pair blocks enter Ceres condensed: P + 1 residuals with the pair's\n"
                     "J^T J, J^T r and cost (the same steps, less per-residual work).")
      .def_readwrite("max_iterations", &BundleAdjusterOptions::max_iterations)
      .def_readwrite("function_tolerance", &BundleAdjusterOptions::function_tolerance)
      .def_readwrite("gradient_tolerance", &BundleAdjusterOptions::gradient_tolerance)
      .def_readwrite("parameter_tolerance", &BundleAdjusterOptions::parameter_tolerance)
      .def_readwrite("num_threads", &BundleAdjusterOptions::num_threads)
      .def_readwrite("use_emt", &BundleAdjusterOptions::use_emt,
                     "Add the EMT pose prior (Eq. 19) for frames with a measurement.")
      .def_readwrite("use_motion_prior", &BundleAdjusterOptions::use_motion_prior,
                     "Add the constant-velocity prior (Eq. 20) for frame ids k-2, k-1, k.")
      .def_readwrite("motion_gate_chi2", &BundleAdjusterOptions::motion_gate_chi2,
                     "Motion gate: after a solve the C_p blocks whose whitened squared norm is\n"
                     "above this (the largest among their neighbours) are left out and the\n"
                     "problem solved again, in rounds, at most a quarter of the blocks (default\n"
                     "22.46, chi2(6) 0.999; inf: off).")
      .def_readwrite("plane_std", &BundleAdjusterOptions::plane_std,
                     "Compute SolveSummary.plane_relative_std (dense in 6 N + 3: small\n"
                     "problems, e.g. the sequential start-up).")
      .def_readwrite("plane_std_paired_only", &BundleAdjusterOptions::plane_std_paired_only,
                     "With plane_std, only the poses of frames in a pair enter the covariance\n"
                     "(the others held: a lower bound; dense in 6 M + 3 for M paired frames).")
      .def("validate", &BundleAdjusterOptions::Validate,
           "Raises ValueError naming the first invalid field.")
      .def("__repr__", [](const py::object& self) {
        return Repr(self, "BundleAdjusterOptions", kOptionFields, std::size(kOptionFields));
      });

  py::class_<SolveSummary>(m, "SolveSummary",
                           "Result of BundleAdjuster.solve(). Costs follow Ceres' convention "
                           "(1/2 sum of squared whitened residuals).")
      .def_readonly("iterations", &SolveSummary::iterations,
                    "Ceres iterations (its iteration 0, the starting evaluation, not counted),\n"
                    "summed over the motion gate's runs; each run at most max_iterations")
      .def_readonly("initial_cost", &SolveSummary::initial_cost,
                    "NaN (as the other costs) where the solve could not evaluate it (FAILURE)")
      .def_readonly("final_cost", &SolveSummary::final_cost)
      .def_readonly("visual_cost", &SolveSummary::visual_cost)
      .def_readonly("emt_cost", &SolveSummary::emt_cost)
      .def_readonly("motion_cost", &SolveSummary::motion_cost)
      .def_readonly("solve_time_s", &SolveSummary::solve_time_s)
      .def_readonly("termination", &SolveSummary::termination)
      .def_readonly("message", &SolveSummary::message)
      .def_readonly("full_report", &SolveSummary::full_report, "Ceres' FullReport().")
      .def_readonly("linear_solver", &SolveSummary::linear_solver)
      .def_readonly("num_residual_blocks", &SolveSummary::num_residual_blocks)
      .def_readonly("num_residuals", &SolveSummary::num_residuals)
      .def_readonly("num_parameters", &SolveSummary::num_parameters)
      .def_readonly("num_free_parameters", &SolveSummary::num_free_parameters)
      .def_readonly("num_visual_blocks", &SolveSummary::num_visual_blocks)
      .def_readonly("num_emt_blocks", &SolveSummary::num_emt_blocks)
      .def_readonly("num_motion_blocks", &SolveSummary::num_motion_blocks)
      .def_readonly("gauge_fixed_by_constraints", &SolveSummary::gauge_fixed_by_constraints)
      .def_readonly("plane_relative_std", &SolveSummary::plane_relative_std,
                    "sqrt(trace(Cov_pi)) / |pi| at the solution with options.plane_std (pi free,\n"
                    "EMT priors, per-pair blocks); NaN otherwise, inf: pi unobservable.")
      .def_readonly("plane_std_time_s", &SolveSummary::plane_std_time_s,
                    "seconds plane_relative_std took (not in solve_time_s); 0 when not computed")
      .def_readonly("motion_released_ids", &SolveSummary::motion_released_ids,
                    "frames whose C_p block the motion gate released in this solve")
      .def(
          "as_dict",
          [](const py::object& self) {
            py::dict out;
            for (const char* field : kSummaryFields) out[field] = self.attr(field);
            return out;
          },
          "All fields as a dict (JSON-serialisable).")
      .def("__repr__", [](const py::object& self) {
        return Repr(self, "SolveSummary", kSummaryFields, std::size(kSummaryFields));
      });

  py::class_<BundleAdjuster>(
      m, "BundleAdjuster",
      "Bundle adjustment of frame poses and the plane: BAVis (use_emt=False) and BAVis+EMT\n"
      "(seed 000, Eq. 17). Owns the parameters, keyed by frame id. Without EMT priors the gauge\n"
      "is fixed by holding the first (lowest-id) frame constant and |plane| fixed. Calls from\n"
      "other threads wait while solve() runs (with the GIL released: only the caller waits).")
      .def(py::init([](const DoubleArray& camera_matrix, const BundleAdjusterOptions& options) {
             return std::make_unique<BundleAdjuster>(CheckCameraMatrix(camera_matrix), options);
           }),
           "camera_matrix"_a, "options"_a = BundleAdjusterOptions(),
           "camera_matrix : (3, 3) float64 K\noptions : BundleAdjusterOptions")
      .def(
          "add_frame",
          [](BundleAdjuster& self, int frame_id, const DoubleArray& cam_from_world,
             const std::optional<DoubleArray>& emt_measurement, double motion_ratio,
             double motion_sigma_scale) {
            const Vector6d x = ToPose(cam_from_world, "cam_from_world");
            std::optional<Vector6d> z;
            if (emt_measurement) z = ToPose(*emt_measurement, "emt_measurement");
            py::gil_scoped_release release;
            self.AddFrame(frame_id, x, z, motion_ratio, motion_sigma_scale);
          },
          "frame_id"_a, "cam_from_world"_a, "emt_measurement"_a = py::none(),
          "motion_ratio"_a = 1.0, "motion_sigma_scale"_a = 1.0,
          "Adds a frame.\n\ncam_from_world : (6,) float64 initial pose [r, t]\n"
          "emt_measurement : (6,) float64 EMT pose z_k [r, t], or None\n"
          "motion_ratio, motion_sigma_scale : timing of the constant-velocity prior over frames\n"
          "    id-2, id-1, id ((t_k - t_k-1) / (t_k-1 - t_k-2) and the sigma_p multiplier; 1, 1\n"
          "    for evenly spaced frames; 0, inf: no prior across a long gap;\n"
          "    estimation.motion.motion_timing)")
      .def(
          "add_pair",
          [](BundleAdjuster& self, int frame_l, int frame_m, const DoubleArray& points_l,
             const DoubleArray& points_m) {
            const BundleAdjuster::Points pl = ToPoints(points_l, "points_l");
            const BundleAdjuster::Points pm = ToPoints(points_m, "points_m");
            py::gil_scoped_release release;
            self.AddPair(frame_l, frame_m, pl, pm);
          },
          "frame_l"_a, "frame_m"_a, "points_l"_a, "points_m"_a,
          "Adds the correspondences of a pair; the residual transfers frame m -> frame l.\n\n"
          "points_l, points_m : (N, 2) float64 pixels, N >= 1, row i corresponds to row i")
      .def(
          "set_plane",
          [](BundleAdjuster& self, const DoubleArray& plane) {
            const Eigen::Vector3d pi = ToPlane(plane);
            py::gil_scoped_release release;
            self.SetPlane(pi);
          },
          "plane"_a, "Sets the plane.\n\nplane : (3,) float64 pi = n / d, non-zero")
      .def(
          "set_pose",
          [](BundleAdjuster& self, int frame_id, const DoubleArray& pose) {
            const Vector6d x = ToPose(pose, "pose");
            py::gil_scoped_release release;
            self.SetPose(frame_id, x);
          },
          "frame_id"_a, "pose"_a, "Sets a frame's pose.\n\npose : (6,) float64 cam_from_world")
      .def("set_constant_frame", &BundleAdjuster::SetConstantFrame, "frame_id"_a,
           "constant"_a = true, py::call_guard<py::gil_scoped_release>(),
           "Holds a frame's pose constant (or frees it again).")
      .def("set_constant_plane", &BundleAdjuster::SetConstantPlane, "constant"_a = true,
           py::call_guard<py::gil_scoped_release>(),
           "Holds the plane constant during solve() (or frees it again).")
      .def("solve", &BundleAdjuster::Solve, py::call_guard<py::gil_scoped_release>(),
           "Runs Ceres (GIL released) and returns a SolveSummary; poses and plane are updated.")
      .def(
          "poses",
          [](const BundleAdjuster& self) {
            std::vector<std::pair<int, Vector6d>> poses;
            {
              py::gil_scoped_release release;
              poses = self.Poses();
            }
            const auto n = static_cast<py::ssize_t>(poses.size());
            py::array_t<int64_t> id_array(n);
            py::array_t<double> pose_array({n, py::ssize_t{kPoseSize}});
            auto id_view = id_array.mutable_unchecked<1>();
            auto pose_view = pose_array.mutable_unchecked<2>();
            for (py::ssize_t i = 0; i < n; ++i) {
              id_view(i) = poses[i].first;
              for (int j = 0; j < kPoseSize; ++j) pose_view(i, j) = poses[i].second[j];
            }
            return py::make_tuple(id_array, pose_array);
          },
          "Returns (ids (N,) int64 ascending, poses (N, 6) float64 cam_from_world).")
      .def(
          "pose", [](const BundleAdjuster& self, int frame_id) { return self.GetPose(frame_id); },
          "frame_id"_a, py::call_guard<py::gil_scoped_release>(),
          "Pose of one frame, (6,) float64. IndexError for an unknown id.")
      .def("plane", &BundleAdjuster::Plane, py::call_guard<py::gil_scoped_release>(),
           "The plane pi = n / d, (3,) float64. ValueError before set_plane.")
      .def_property_readonly(
          "options", [](const BundleAdjuster& self) { return self.options(); },
          "A copy of the options (fixed at construction).")
      .def_property_readonly("camera_matrix",
                             [](const BundleAdjuster& self) { return self.camera_matrix(); })
      .def_property_readonly("num_frames", Released(&BundleAdjuster::NumFrames))
      .def_property_readonly("num_pairs", Released(&BundleAdjuster::NumPairs))
      .def_property_readonly("num_correspondences",
                             Released(&BundleAdjuster::NumCorrespondences));
}

}  // namespace fusedmosaic::bindings
