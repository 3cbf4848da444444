// Camera poses: angle-axis rotation + translation, cam_from_world.
//
// Conventions used throughout fusedmosaic (seed 000, Sec. 3.3.1, Eq. 4 and 7):
//  * A pose is a 6-vector x = [r, t]: x[0..2] angle-axis r (rad), x[3..5] translation t (mm).
//  * It maps world points into the camera: X_cam = R(r) * X_world + t (cam_from_world).
//  * R(r) = exp([r]_x), the right-handed Rodrigues rotation (Ceres' AngleAxisToRotationMatrix).
//  * World is the tracker frame after hand-eye; the paper's virtual camera sits at its origin.
//  * Quaternions at the I/O boundary are unit Hamilton quaternions stored (x, y, z, w), as in
//    SciPy's Rotation.from_quat; in C++ Eigen::Quaternion is used, never a raw 4-array.
// Everything here is templated on the scalar so that doubles and ceres::Jet share one code path.
#pragma once

#include <ceres/rotation.h>

#include <Eigen/Core>
#include <Eigen/LU>

namespace fusedmosaic {

template <typename T>
using Vector3 = Eigen::Matrix<T, 3, 1>;
template <typename T>
using Matrix3 = Eigen::Matrix<T, 3, 3>;

inline constexpr int kPoseSize = 6;   // [r(3), t(3)]
inline constexpr int kPlaneSize = 3;  // pi = n / d

// R(r) for an angle-axis vector r (3 values).
template <typename T>
Matrix3<T> RotationFromAngleAxis(const T* angle_axis) {
  Matrix3<T> R;
  ceres::AngleAxisToRotationMatrix(angle_axis, ceres::ColumnMajorAdapter3x3(R.data()));
  return R;
}

// Inverse of RotationFromAngleAxis; |r| in [0, pi].
template <typename T>
Vector3<T> AngleAxisFromRotation(const Matrix3<T>& R) {
  Vector3<T> r;
  ceres::RotationMatrixToAngleAxis(ceres::ColumnMajorAdapter3x3(R.data()), r.data());
  return r;
}

// A rigid transform in matrix form, b_from_a, built from / stored into a 6-vector pose.
template <typename T>
struct RigidTransform {
  Matrix3<T> rotation = Matrix3<T>::Identity();
  Vector3<T> translation = Vector3<T>::Zero();

  static RigidTransform FromPose(const T* pose) {
    RigidTransform out;
    out.rotation = RotationFromAngleAxis(pose);
    out.translation = Vector3<T>(pose[3], pose[4], pose[5]);
    return out;
  }

  void ToPose(T* pose) const {
    const Vector3<T> r = AngleAxisFromRotation(rotation);
    for (int i = 0; i < 3; ++i) {
      pose[i] = r[i];
      pose[3 + i] = translation[i];
    }
  }

  // (c_from_b * b_from_a) = c_from_a.
  RigidTransform operator*(const RigidTransform& b_from_a) const {
    RigidTransform out;
    out.rotation = rotation * b_from_a.rotation;
    out.translation = rotation * b_from_a.translation + translation;
    return out;
  }

  RigidTransform Inverse() const {
    RigidTransform out;
    out.rotation = rotation.transpose();
    out.translation = -(out.rotation * translation);
    return out;
  }
};

// Camera centre in world coordinates: C = -R^T t.
template <typename T>
Vector3<T> CameraCenter(const T* cam_from_world) {
  const Matrix3<T> R = RotationFromAngleAxis(cam_from_world);
  const Vector3<T> t(cam_from_world[3], cam_from_world[4], cam_from_world[5]);
  return -(R.transpose() * t);
}

}  // namespace fusedmosaic
