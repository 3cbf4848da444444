// Motion gate (not in the paper): release the constant-velocity terms (Eq. 20) of a solved
// problem that its solution contradicts (BundleAdjusterOptions::motion_gate_chi2).
#pragma once

#include <ceres/problem.h>

#include <vector>

namespace fusedmosaic {

// The C_p blocks of a problem, the frame (k of the triple k-2, k-1, k) each belongs to, and
// whether the gate may judge it (MotionJudged).
struct MotionBlocks {
  std::vector<ceres::ResidualBlockId> blocks;
  std::vector<int> frame_ids;
  std::vector<bool> judged;

  void Add(ceres::ResidualBlockId block, int frame_id, bool visual) {
    blocks.push_back(block);
    frame_ids.push_back(frame_id);
    judged.push_back(visual);
  }
};

// Whether a solve may release frame k's C_p: only a frame with visual residuals (the images
// then place it; a frame without keeps C_p, its only hold besides its tracker sample), and only
// when a frame of the triple has no tracker sample: where all three have one, the tracker has
// judged the motion already (estimation/motion.py motion_verdict, the caller's check), and
// a solution that leaves C_p far off was pulled by something else (a +20 deg glitch on a black
// frame spread into its textured neighbours' C_p: released, the black frame went 48 px off
// instead of 27).
inline bool MotionJudged(bool visual, bool tracked_km2, bool tracked_km1, bool tracked_k) {
  return visual && !(tracked_km2 && tracked_km1 && tracked_k);
}

// At the current parameter values, the judged blocks whose whitened squared norm
// |S_p (x_k - mu_p)|^2 is above gate_chi2 and the largest among the blocks sharing a camera
// with them (frames within 2) are removed from `problem` and from `motion`, the largest first,
// at most max_releases; returns their frame ids. A block above the gate only because its
// neighbour's violation spread into it stays until that one is gone and the problem solved
// again; violations far apart go in one round.
std::vector<int> ReleaseMotionBlocks(ceres::Problem* problem, MotionBlocks* motion,
                                     double gate_chi2, int max_releases);

// How many blocks one solve may release in all: a quarter of them (at least one), none when
// the gate is off (inf). The gate judges a block against the others, so most must stay.
int MaxMotionReleases(int num_blocks, double gate_chi2);

}  // namespace fusedmosaic
