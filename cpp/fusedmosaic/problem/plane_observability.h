// Observability of the plane in a solved problem (the sliding window's plane gate, the
// sequential start-up's check).
#pragma once

#include <ceres/problem.h>

#include <vector>

namespace fusedmosaic {

// sqrt(trace(Cov_pi)) / plane_norm at the current parameter values: the marginal covariance of
// the plane (kPlaneSize values at `plane`) given every residual block touching `plane` or one
// of `free_poses`, Cov = (J^T J)^+ (residuals whitened by their sigmas, so it is absolute).
// inf when a direction without information moves pi. Dense: (6 N + 3)^2 for N free poses.
double PlaneRelativeStd(ceres::Problem* problem, double* plane,
                        const std::vector<double*>& free_poses, double plane_norm);

}  // namespace fusedmosaic
