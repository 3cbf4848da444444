// Plane-induced homographies and point transfer (seed 000, Eqs. 1-5 and 13).
//
// In normalised coordinates (p = K^-1 q), the plane pi induces for camera k
//     H_k = R_k - t_k pi^T                                              (Eq. 5 without K)
// mapping virtual-camera points to frame-k points: for X on the plane -pi^T X = 1, hence
// R X + t = (R - t pi^T) X. Pixel homographies are K H_k K^-1. A point of frame m transfers to
// frame l through H_l H_m^-1 (Eq. 3, 13). The frame -> reference homography written to
// homographies.csv is G_k = H_0 H_k^-1 in pixels, normalised so G_k[2,2] = 1.
#pragma once

#include "fusedmosaic/geometry/plane.h"
#include "fusedmosaic/geometry/pose.h"

namespace fusedmosaic {

// H = R - t pi^T in normalised coordinates. pose: x[0..2] angle-axis, x[3..5] translation.
template <typename T>
Matrix3<T> InducedHomography(const T* cam_from_world, const T* plane) {
  const Vector3<T> t(cam_from_world[3], cam_from_world[4], cam_from_world[5]);
  const Vector3<T> pi(plane[0], plane[1], plane[2]);
  return RotationFromAngleAxis(cam_from_world) - t * pi.transpose();
}

// H_l H_m^-1: maps normalised points of frame m to frame l (unnormalised scale).
template <typename T>
Matrix3<T> TransferHomography(const T* cam_l_from_world, const T* cam_m_from_world,
                              const T* plane) {
  return InducedHomography(cam_l_from_world, plane) *
         InducedHomography(cam_m_from_world, plane).inverse();
}

// Applies a homography to an inhomogeneous 2D point.
template <typename T>
Eigen::Matrix<T, 2, 1> ApplyHomography(const Matrix3<T>& H, const Eigen::Matrix<T, 2, 1>& p) {
  const Vector3<T> q = H * Vector3<T>(p[0], p[1], T(1));
  return Eigen::Matrix<T, 2, 1>(q[0] / q[2], q[1] / q[2]);
}

// Conjugates a normalised-coordinate homography into pixels: K H K^-1.
template <typename T>
Matrix3<T> ToPixels(const Matrix3<T>& H, const Eigen::Matrix3d& K) {
  const Matrix3<T> Kt = K.cast<T>();
  const Matrix3<T> Kinv = K.inverse().cast<T>();
  return Kt * H * Kinv;
}

// Scales H so that H(2,2) = 1.
template <typename T>
Matrix3<T> NormalizeHomography(const Matrix3<T>& H) {
  return H / H(2, 2);
}

}  // namespace fusedmosaic
