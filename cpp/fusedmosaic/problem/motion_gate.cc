#include "fusedmosaic/problem/motion_gate.h"

#include <algorithm>
#include <cmath>

namespace fusedmosaic {

std::optional<int> ReleaseWorstMotionBlock(ceres::Problem* problem, MotionBlocks* motion,
                                           double gate_chi2) {
  double worst = gate_chi2;
  int worst_index = -1;
  for (size_t i = 0; i < motion->blocks.size(); ++i) {
    double cost = 0.0;  // 1/2 |r|^2: the block has no loss function
    problem->EvaluateResidualBlock(motion->blocks[i], /*apply_loss_function=*/false, &cost,
                                   nullptr, nullptr);
    if (2.0 * cost > worst) {
      worst = 2.0 * cost;
      worst_index = static_cast<int>(i);
    }
  }
  if (worst_index < 0) return std::nullopt;
  const int frame_id = motion->frame_ids[worst_index];
  problem->RemoveResidualBlock(motion->blocks[worst_index]);
  motion->blocks.erase(motion->blocks.begin() + worst_index);
  motion->frame_ids.erase(motion->frame_ids.begin() + worst_index);
  return frame_id;
}

int MaxMotionReleases(int num_blocks, double gate_chi2) {
  if (!std::isfinite(gate_chi2) || num_blocks == 0) return 0;
  return std::max(1, num_blocks / 4);
}

}  // namespace fusedmosaic
