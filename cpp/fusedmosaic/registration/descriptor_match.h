// Exact nearest-neighbour matching of descriptors with Lowe's ratio test and a one-to-one filter
// (seed 000, Sec. 3.1: correspondences of a pair): binary descriptors (ORB) under the Hamming
// distance, exhaustive or guided; float descriptors (SIFT) under the Euclidean distance, guided
// (exhaustively, OpenCV's brute-force matcher is as fast).
//
// For every query descriptor the two nearest train descriptors are found by brute force; the
// query is kept if d1 < ratio * d2 (a unique best), and of the queries kept for one train
// descriptor only the nearest survives (the first in query order on a tie). This is what
// cv2.BFMatcher(NORM_HAMMING).knnMatch(k=2) followed by the same two filters gives, computed
// with the CPU's popcount instruction: the OpenCV wheels are built for an SSE3 baseline, so their
// Hamming norm counts bits by table look-up. On the 2-core Xeon of the benchmarks (1000 x 1000
// ORB descriptors, 32 bytes): OpenCV brute force 7.9 ms, OpenCV's FLANN LSH (approximate) 5.1 ms,
// this 2.4 ms (bench/bench_sequential.py reports the matching stage per frame).
#pragma once

#include <cstdint>
#include <vector>

namespace fusedmosaic {

template <typename Distance>
struct Matches {
  std::vector<int> query;           // query descriptor row, ascending
  std::vector<int> train;           // its matched train descriptor row
  std::vector<Distance> distance;  // their distance
};
using HammingMatches = Matches<int>;  // distances in bits
using L2Matches = Matches<float>;     // Euclidean distances

// query: (num_query, bytes) and train: (num_train, bytes) row-major uint8 descriptors.
// ratio in (0, 1]. Fewer than two train descriptors: no match passes the ratio test.
// Throws std::invalid_argument on bytes <= 0 or a ratio outside (0, 1].
HammingMatches MatchHammingRatio(const std::uint8_t* query, int num_query,
                                 const std::uint8_t* train, int num_train, int bytes,
                                 double ratio);

// The same search restricted to train descriptors whose keypoint lies within `radius` pixels of
// the query's predicted position (guided matching, as when a motion model predicts where a
// keypoint reappears: ORB-SLAM's search by projection). query_xy: (num_query, 2) predicted
// positions in the train image (a non-finite one: the query is not matched); train_xy:
// (num_train, 2). The ratio test compares the two nearest candidates inside the radius. A query
// with a single candidate is kept when its distance is at most max_distance bits (ORB-SLAM's
// absolute threshold) or, with max_distance < 0, when it passes the ratio test against the
// nearest of all the other train descriptors (what the exhaustive search would test it against:
// sparse keypoints, such as SIFT's ~100 on a low-texture frame, often leave one candidate in
// the radius). Candidates are found through a grid of radius-sized cells, so the cost grows
// with the candidates per query (plus num_train per lone candidate) instead of num_train. Throws std::invalid_argument on bytes <= 0, a ratio
// outside (0, 1] or a radius that is not positive and finite.
HammingMatches MatchHammingGuided(const std::uint8_t* query, const double* query_xy,
                                  int num_query, const std::uint8_t* train,
                                  const double* train_xy, int num_train, int bytes,
                                  double radius, double ratio, int max_distance);

// MatchHammingGuided for float descriptors (SIFT: dims = 128) under the Euclidean distance:
// query (num_query, dims), train (num_train, dims) row-major float32. The ratio test compares
// Euclidean distances (as cv2.BFMatcher(NORM_L2)'s do), a lone candidate as above with
// max_distance in the same units; distances are returned. A descriptor with a
// non-finite element matches nothing. Throws std::invalid_argument on dims <= 0, a ratio outside
// (0, 1], a radius that is not positive and finite, or a NaN max_distance.
L2Matches MatchL2Guided(const float* query, const double* query_xy, int num_query,
                        const float* train, const double* train_xy, int num_train, int dims,
                        double radius, double ratio, double max_distance);

}  // namespace fusedmosaic
