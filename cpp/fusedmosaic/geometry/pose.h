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

#include <ceres/jet.h>
#include <ceres/rotation.h>

#include <cmath>

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

// The value of a double or of a ceres::Jet (its scalar part): discrete choices, such as which
// angle-axis vector stands for a rotation, are made on values; derivatives flow through the
// expression chosen.
inline double ValueOf(double v) { return v; }
template <typename T, int N>
double ValueOf(const ceres::Jet<T, N>& v) {
  return ValueOf(v.a);
}

// r_a - r_b' for two angle-axis vectors, r_b' the angle-axis vector of the rotation R(r_b) that
// is nearest r_a. A rotation by theta about the unit axis u has the vectors u (theta + 2 pi n),
// n integer (all of norm 2 pi n for the identity): near theta = pi, +pi u and -pi u are one
// rotation 2 pi apart, and the plain difference of two rotations 0.02 rad apart can be ~2 pi.
// Along u, |r_a - u (theta + 2 pi n)| is least for n = round((u . r_a - theta) / (2 pi)): n = 0
// whenever the plain difference has a component along u below pi, which leaves the plain
// difference itself, bit for bit (every error a prior sees in normal operation). Unless
// R(r_b) = I, the chosen vector depends on r_b alone (a constant, or the Jet of a prediction),
// so d/dr_a = I as for the plain difference. What remains of the angle-axis chart: near |r| = pi its directions
// across u are stretched, theta / (2 sin(theta / 2)) <= pi / 2 times the geodesic angle; and at
// |r_a| near 2 pi the rotations near the identity spread over a sphere (estimates start from
// vectors of norm <= pi, ToPose's, and move by their errors: they do not get there).
template <typename T>
Vector3<T> AngleAxisDifference(const T* r_a, const T* r_b) {
  using std::sqrt;
  constexpr double kTwoPi = 6.283185307179586476925;
  const Vector3<T> a(r_a[0], r_a[1], r_a[2]);
  const Vector3<T> b(r_b[0], r_b[1], r_b[2]);
  const Eigen::Vector3d a_value(ValueOf(r_a[0]), ValueOf(r_a[1]), ValueOf(r_a[2]));
  const Eigen::Vector3d b_value(ValueOf(r_b[0]), ValueOf(r_b[1]), ValueOf(r_b[2]));
  const double theta_b = b_value.norm();
  if (theta_b > 0.0) {
    const double n = std::round((b_value.dot(a_value) / theta_b - theta_b) / kTwoPi);
    if (n == 0.0) return a - b;
    return a - b * (T(1.0) + T(kTwoPi * n) / sqrt(b.squaredNorm()));
  }
  // R(r_b) = I: the vector of norm 2 pi n along r_a.
  const double n = std::round(a_value.norm() / kTwoPi);
  if (n == 0.0) return a - b;
  return a - a * (T(kTwoPi * n) / sqrt(a.squaredNorm()));
}

// x - z for two poses [r, t]: the rotations by AngleAxisDifference (z's angle-axis vector the
// one of its rotation nearest x's), the translations plainly. The priors' residual (pose_prior.h,
// constant_velocity.h).
template <typename T>
void PoseDifference(const T* x, const T* z, T* difference) {
  const Vector3<T> dr = AngleAxisDifference(x, z);
  for (int i = 0; i < 3; ++i) {
    difference[i] = dr[i];
    difference[3 + i] = x[3 + i] - z[3 + i];
  }
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
