// Motion gate (not in the paper): release the constant-velocity term (Eq. 20) of a solved
// problem that its solution contradicts (BundleAdjusterOptions::motion_gate_chi2).
#pragma once

#include <ceres/problem.h>

#include <optional>
#include <vector>

namespace fusedmosaic {

// The C_p blocks of a problem and the frame (k of the triple k-2, k-1, k) each belongs to.
struct MotionBlocks {
  std::vector<ceres::ResidualBlockId> blocks;
  std::vector<int> frame_ids;

  void Add(ceres::ResidualBlockId block, int frame_id) {
    blocks.push_back(block);
    frame_ids.push_back(frame_id);
  }
};

// At the current parameter values: the block whose whitened squared norm |S_p (x_k - mu_p)|^2
// is largest and above gate_chi2 is removed from `problem` and from `motion`; returns its frame
// id, or nothing when no block exceeds the gate.
std::optional<int> ReleaseWorstMotionBlock(ceres::Problem* problem, MotionBlocks* motion,
                                           double gate_chi2);

// How many blocks one solve may release: a quarter of them (at least one), none when the gate
// is off (inf). The gate judges a block against the others, so most must stay.
int MaxMotionReleases(int num_blocks, double gate_chi2);

}  // namespace fusedmosaic
