// The scene plane, parametrised as pi = n / d (seed 000, Sec. 3.3.1).
//
// The plane is { X : n.X + d = 0 } seen from the virtual camera (world origin), with n a unit
// normal and d its signed offset; pi = n / d is unique for a plane not through the origin and
// carries the inverse depth 1/|d| in its norm. For any X on the plane, -pi^T X = 1, which is what
// makes the induced homography R - t pi^T (homography.h) exact.
#pragma once

#include <cmath>

#include "fusedmosaic/geometry/pose.h"

namespace fusedmosaic {

// pi from a (not necessarily unit) normal and offset d != 0.
template <typename T>
Vector3<T> PlaneFromNormalDistance(const Vector3<T>& normal, const T& d) {
  return normal / (normal.norm() * d);
}

// Distance from the virtual camera (world origin) to the plane: 1 / |pi|.
template <typename T>
T OriginPlaneDistance(const T* plane) {
  using std::sqrt;
  return T(1) / sqrt(plane[0] * plane[0] + plane[1] * plane[1] + plane[2] * plane[2]);
}

// Unsigned distance from the camera centre of `cam_from_world` to the plane:
// |n.C + d| = |d| |pi.C + 1| = |pi.C + 1| / |pi|.
template <typename T>
T CameraPlaneDistance(const T* cam_from_world, const T* plane) {
  using std::abs;
  const Vector3<T> C = CameraCenter(cam_from_world);
  const Vector3<T> pi(plane[0], plane[1], plane[2]);
  return abs(pi.dot(C) + T(1)) * OriginPlaneDistance(plane);
}

}  // namespace fusedmosaic
