// The visual transfer cost's factories: the four VisualTransferCostFunction instantiations
// (free cameras l / m) are compiled here once rather than in every file that builds problems.
#include "fusedmosaic/residuals/visual_transfer.h"

#include <utility>

namespace fusedmosaic {

ceres::CostFunction* CreateVisualTransferCost(VisualTransferCostFunctor transfer,
                                              const double* fixed_l, const double* fixed_m,
                                              bool condense) {
  if (fixed_l == nullptr && fixed_m == nullptr) {
    return new VisualTransferCostFunction<true, true>(std::move(transfer), nullptr, nullptr,
                                                      condense);
  }
  if (fixed_l == nullptr) {
    return new VisualTransferCostFunction<true, false>(std::move(transfer), nullptr, fixed_m,
                                                       condense);
  }
  if (fixed_m == nullptr) {
    return new VisualTransferCostFunction<false, true>(std::move(transfer), fixed_l, nullptr,
                                                       condense);
  }
  return new VisualTransferCostFunction<false, false>(std::move(transfer), fixed_l, fixed_m,
                                                      condense);
}

ceres::CostFunction* VisualTransferCostFunctor::Create(const Eigen::Matrix3d& camera_matrix,
                                                       const Matrix2Xd& points_l,
                                                       const Matrix2Xd& points_m, double sigma_v,
                                                       RobustLoss loss, double loss_scale) {
  return CreateVisualTransferCost(
      VisualTransferCostFunctor(camera_matrix, points_l, points_m, sigma_v, loss, loss_scale));
}

}  // namespace fusedmosaic
