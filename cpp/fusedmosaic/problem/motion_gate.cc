#include "fusedmosaic/problem/motion_gate.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <utility>

namespace fusedmosaic {

std::vector<int> ReleaseMotionBlocks(ceres::Problem* problem, MotionBlocks* motion,
                                     double gate_chi2, int max_releases) {
  const size_t n = motion->blocks.size();
  std::vector<double> m2(n);
  for (size_t i = 0; i < n; ++i) {
    double cost = 0.0;  // 1/2 |r|^2: the block has no loss function
    problem->EvaluateResidualBlock(motion->blocks[i], /*apply_loss_function=*/false, &cost,
                                   nullptr, nullptr);
    m2[i] = 2.0 * cost;
  }
  std::vector<std::pair<double, size_t>> chosen;  // (m2, index), local maxima above the gate
  for (size_t i = 0; i < n; ++i) {
    if (!motion->judged[i] || !(m2[i] > gate_chi2)) continue;
    bool largest = true;
    for (size_t j = 0; j < n && largest; ++j) {
      if (j == i || std::abs(motion->frame_ids[j] - motion->frame_ids[i]) > 2) continue;
      // ties: the earlier frame goes first
      largest = m2[j] < m2[i] || (m2[j] == m2[i] && motion->frame_ids[i] < motion->frame_ids[j]);
    }
    if (largest) chosen.emplace_back(m2[i], i);
  }
  std::sort(chosen.begin(), chosen.end(),
            [](const auto& a, const auto& b) { return a.first > b.first; });
  if (static_cast<int>(chosen.size()) > max_releases) chosen.resize(std::max(0, max_releases));
  std::vector<size_t> remove;
  std::vector<int> frame_ids;
  for (const auto& c : chosen) {
    remove.push_back(c.second);
    frame_ids.push_back(motion->frame_ids[c.second]);
    problem->RemoveResidualBlock(motion->blocks[c.second]);
  }
  std::sort(remove.rbegin(), remove.rend());
  for (size_t i : remove) {
    motion->blocks.erase(motion->blocks.begin() + static_cast<long>(i));
    motion->frame_ids.erase(motion->frame_ids.begin() + static_cast<long>(i));
    motion->judged.erase(motion->judged.begin() + static_cast<long>(i));
  }
  return frame_ids;
}

int MaxMotionReleases(int num_blocks, double gate_chi2) {
  if (!std::isfinite(gate_chi2) || num_blocks == 0) return 0;
  return std::max(1, num_blocks / 4);
}

}  // namespace fusedmosaic
