// Python bindings of cpp/fusedmosaic/geometry (double instantiations).
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cmath>
#include <optional>
#include <string>

#include "bindings/bind.h"
#include "fusedmosaic/geometry/homography.h"
#include "fusedmosaic/geometry/plane.h"
#include "fusedmosaic/geometry/pose.h"
#include "fusedmosaic/residuals/pose_prior.h"  // Vector6d

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

// Throws when the camera centre is on the plane: H = R - t pi^T is then singular (transfers
// through it map every point to one line, or to infinity).
void CheckInvertible(const Eigen::Matrix3d& H, const std::string& what) {
  const double det = H.determinant();
  if (!std::isfinite(det) || std::abs(det) < 1e-12 * std::pow(H.norm(), 3)) {
    throw std::invalid_argument(what +
                                ": induced homography is singular (camera centre on the plane)");
  }
}

Eigen::Matrix3d CheckedInverse(const Eigen::Matrix3d& H, const std::string& what) {
  CheckInvertible(H, what);
  return H.inverse();
}

Eigen::Matrix3d Induced(const DoubleArray& pose, const Eigen::Vector3d& plane, const char* name) {
  const Vector6d x = ToVector(pose, kPoseSize, name);
  return InducedHomography(x.data(), plane.data());
}

// H_l H_m^-1 (Eq. 13). Camera l on the plane is refused as camera m is: H_l singular gave a
// rank-2 transfer, inf / NaN once normalised, instead of an error.
Eigen::Matrix3d Transfer(const DoubleArray& cam_l_from_world, const DoubleArray& cam_m_from_world,
                         const Eigen::Vector3d& plane) {
  const Eigen::Matrix3d Hl = Induced(cam_l_from_world, plane, "cam_l_from_world");
  const Eigen::Matrix3d Hm = Induced(cam_m_from_world, plane, "cam_m_from_world");
  CheckInvertible(Hl, "cam_l_from_world");
  return Hl * CheckedInverse(Hm, "cam_m_from_world");
}

Eigen::Matrix3d MaybePixels(const Eigen::Matrix3d& H, const std::optional<DoubleArray>& K) {
  if (!K) return H;
  return ToPixels<double>(H, CheckCameraMatrix(*K));
}

}  // namespace

void BindGeometry(py::module_& m) {
  m.def(
      "rotation_from_angle_axis",
      [](const DoubleArray& angle_axis) -> Eigen::Matrix3d {
        const Eigen::Vector3d r = ToVector(angle_axis, 3, "angle_axis");
        return RotationFromAngleAxis(r.data());
      },
      "angle_axis"_a,
      "Rotation matrix R = exp([r]_x).\n\nangle_axis : (3,) float64, radians\nReturns (3, 3).");

  m.def(
      "angle_axis_from_rotation",
      [](const DoubleArray& rotation) -> Eigen::Vector3d {
        const Eigen::Matrix3d R = ToMatrix(rotation, 3, 3, "rotation");
        if ((R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-6 ||
            R.determinant() < 0) {
          throw std::invalid_argument("rotation: not a rotation matrix (R^T R != I or det < 0)");
        }
        return AngleAxisFromRotation(R);
      },
      "rotation"_a, "Angle-axis vector of a rotation matrix.\n\nrotation : (3, 3) float64");

  m.def(
      "compose_poses",
      [](const DoubleArray& c_from_b, const DoubleArray& b_from_a) -> Eigen::VectorXd {
        const Vector6d cb = ToVector(c_from_b, kPoseSize, "c_from_b");
        const Vector6d ba = ToVector(b_from_a, kPoseSize, "b_from_a");
        const auto out = RigidTransform<double>::FromPose(cb.data()) *
                         RigidTransform<double>::FromPose(ba.data());
        Eigen::VectorXd pose(kPoseSize);
        out.ToPose(pose.data());
        return pose;
      },
      "c_from_b"_a, "b_from_a"_a,
      "c_from_a = c_from_b * b_from_a for 6-vector poses [r, t].\n\nReturns (6,).");

  m.def(
      "invert_pose",
      [](const DoubleArray& b_from_a) -> Eigen::VectorXd {
        const Vector6d ba = ToVector(b_from_a, kPoseSize, "b_from_a");
        Eigen::VectorXd pose(kPoseSize);
        RigidTransform<double>::FromPose(ba.data()).Inverse().ToPose(pose.data());
        return pose;
      },
      "b_from_a"_a, "a_from_b for a 6-vector pose [r, t].\n\nReturns (6,).");

  m.def(
      "camera_plane_distance",
      [](const DoubleArray& cam_from_world, const DoubleArray& plane) {
        const Vector6d x = ToVector(cam_from_world, kPoseSize, "cam_from_world");
        const Eigen::Vector3d pi = ToPlane(plane);
        return CameraPlaneDistance(x.data(), pi.data());
      },
      "cam_from_world"_a, "plane"_a, "Distance from the camera centre to the plane (mm).");

  m.def(
      "induced_homography",
      [](const DoubleArray& cam_from_world, const DoubleArray& plane,
         const std::optional<DoubleArray>& camera_matrix) -> Eigen::Matrix3d {
        const Eigen::Vector3d pi = ToPlane(plane);
        return MaybePixels(Induced(cam_from_world, pi, "cam_from_world"), camera_matrix);
      },
      "cam_from_world"_a, "plane"_a, "camera_matrix"_a = py::none(),
      "H_k = K (R - t pi^T) K^-1 (Eq. 5): virtual-camera pixels -> frame-k pixels.\n\n"
      "cam_from_world : (6,) float64 [r, t]\nplane : (3,) float64 pi = n/d\n"
      "camera_matrix : (3, 3) float64 or None (normalised coordinates)\nReturns (3, 3).");

  m.def(
      "transfer_homography",
      [](const DoubleArray& cam_l_from_world, const DoubleArray& cam_m_from_world,
         const DoubleArray& plane,
         const std::optional<DoubleArray>& camera_matrix) -> Eigen::Matrix3d {
        const Eigen::Vector3d pi = ToPlane(plane);
        return NormalizeHomography<double>(
            MaybePixels(Transfer(cam_l_from_world, cam_m_from_world, pi), camera_matrix));
      },
      "cam_l_from_world"_a, "cam_m_from_world"_a, "plane"_a, "camera_matrix"_a = py::none(),
      "H_l H_m^-1 (Eq. 13): frame-m points -> frame-l points, normalised to H[2,2] = 1.");

  m.def(
      "transfer_points",
      [](const DoubleArray& points, const DoubleArray& cam_l_from_world,
         const DoubleArray& cam_m_from_world, const DoubleArray& plane,
         const std::optional<DoubleArray>& camera_matrix) -> RowMatrixXd {
        const auto p = ToMatrix(points, -1, 2, "points");
        const Eigen::Vector3d pi = ToPlane(plane);
        const Eigen::Matrix3d H =
            MaybePixels(Transfer(cam_l_from_world, cam_m_from_world, pi), camera_matrix);
        RowMatrixXd out(p.rows(), 2);
        for (Eigen::Index i = 0; i < p.rows(); ++i) {
          out.row(i) = ApplyHomography<double>(H, p.row(i).transpose()).transpose();
        }
        return out;
      },
      "points"_a, "cam_l_from_world"_a, "cam_m_from_world"_a, "plane"_a,
      "camera_matrix"_a = py::none(),
      "Transfers points of frame m into frame l through the plane (Eq. 13).\n\n"
      "points : (N, 2) float64\nReturns (N, 2).");

  m.def(
      "frame_to_reference",
      [](const DoubleArray& cams_from_world_array, const DoubleArray& plane_array,
         const DoubleArray& camera_matrix, int reference) -> py::array_t<double> {
        const auto cams_from_world =
            ToMatrix(cams_from_world_array, -1, kPoseSize, "cams_from_world");
        const Eigen::Vector3d plane = ToPlane(plane_array);
        const Eigen::Matrix3d K = CheckCameraMatrix(camera_matrix);
        const Eigen::Index n = cams_from_world.rows();
        if (reference < 0 || reference >= n) {
          throw std::out_of_range("reference: index " + std::to_string(reference) +
                                  " outside [0, " + std::to_string(n) + ")");
        }
        const Eigen::VectorXd ref_pose = cams_from_world.row(reference).transpose();
        const Eigen::Matrix3d H0 = InducedHomography(ref_pose.data(), plane.data());
        py::array_t<double> out({static_cast<py::ssize_t>(n), py::ssize_t{3}, py::ssize_t{3}});
        auto view = out.mutable_unchecked<3>();
        for (Eigen::Index k = 0; k < n; ++k) {
          const Eigen::VectorXd pose = cams_from_world.row(k).transpose();
          const Eigen::Matrix3d Hk = InducedHomography(pose.data(), plane.data());
          // The row named: one degenerate pose fails the whole table.
          const Eigen::Matrix3d G = NormalizeHomography<double>(ToPixels<double>(
              H0 * CheckedInverse(Hk, "cams_from_world[" + std::to_string(k) + "]"), K));
          for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) view(k, i, j) = G(i, j);
        }
        return out;
      },
      "cams_from_world"_a, "plane"_a, "camera_matrix"_a, "reference"_a = 0,
      "Frame -> reference pixel homographies G_k = H_ref H_k^-1 (design: output contract).\n\n"
      "cams_from_world : (N, 6) float64\nplane : (3,) float64\ncamera_matrix : (3, 3) float64\n"
      "Returns (N, 3, 3), each normalised so G[2,2] = 1.");
}

}  // namespace fusedmosaic::bindings
