#include "fusedmosaic/registration/hamming_match.h"

#include <climits>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>

namespace fusedmosaic {
namespace {

struct TwoNearest {
  int best = INT_MAX, second = INT_MAX, index = -1;

  void Add(int d, int j) {
    if (d < best) {
      second = best;
      best = d;
      index = j;
    } else if (d < second) {
      second = d;
    }
  }
};

// Distances from one query to every train row; the two smallest. Words: descriptor length in
// 64-bit words when fixed at compile time (ORB: 4), 0 for any length.
template <int Words>
inline TwoNearest NearestTwo(const std::uint8_t* q, const std::uint8_t* train, int num_train,
                             int bytes) {
  TwoNearest out;
  const int words = Words > 0 ? Words : bytes / 8;
  std::uint64_t qw[Words > 0 ? Words : 1];
  if constexpr (Words > 0) std::memcpy(qw, q, sizeof(qw));
  for (int j = 0; j < num_train; ++j) {
    const std::uint8_t* t = train + static_cast<size_t>(j) * bytes;
    int d = 0;
    for (int w = 0; w < words; ++w) {
      std::uint64_t a, b;
      if constexpr (Words > 0) {
        a = qw[w];
      } else {
        std::memcpy(&a, q + 8 * w, 8);
      }
      std::memcpy(&b, t + 8 * w, 8);
      d += __builtin_popcountll(a ^ b);
    }
    if constexpr (Words == 0) {
      for (int k = 8 * words; k < bytes; ++k) d += __builtin_popcount(q[k] ^ t[k]);
    }
    out.Add(d, j);
  }
  return out;
}

// The nearest two of every query.
__attribute__((always_inline)) inline void NearestTwoOfEach(const std::uint8_t* query,
                                                            int num_query,
                                                            const std::uint8_t* train,
                                                            int num_train, int bytes,
                                                            TwoNearest* out) {
  for (int i = 0; i < num_query; ++i) {
    const std::uint8_t* q = query + static_cast<size_t>(i) * bytes;
    out[i] = bytes == 32 ? NearestTwo<4>(q, train, num_train, bytes)
                         : NearestTwo<0>(q, train, num_train, bytes);
  }
}

// Built twice: with the popcount instruction (NearestTwoOfEach inlined into a popcnt-target
// function), picked at run time on CPUs that have it (every x86-64 since ~2008), and without (a
// bit-counting routine), so the module never executes an instruction the CPU lacks.
#if defined(__x86_64__) && defined(__GNUC__)
#define FUSEDMOSAIC_HAVE_POPCNT_CLONE 1
__attribute__((target("popcnt"))) void NearestTwoOfEachPopcnt(const std::uint8_t* query,
                                                              int num_query,
                                                              const std::uint8_t* train,
                                                              int num_train, int bytes,
                                                              TwoNearest* out) {
  NearestTwoOfEach(query, num_query, train, num_train, bytes, out);
}
#endif

void AllNearestTwo(const std::uint8_t* query, int num_query, const std::uint8_t* train,
                   int num_train, int bytes, TwoNearest* out) {
#ifdef FUSEDMOSAIC_HAVE_POPCNT_CLONE
  if (__builtin_cpu_supports("popcnt")) {
    NearestTwoOfEachPopcnt(query, num_query, train, num_train, bytes, out);
    return;
  }
#endif
  NearestTwoOfEach(query, num_query, train, num_train, bytes, out);
}

}  // namespace

HammingMatches MatchHammingRatio(const std::uint8_t* query, int num_query,
                                 const std::uint8_t* train, int num_train, int bytes,
                                 double ratio) {
  if (bytes <= 0) {
    throw std::invalid_argument("descriptors: expected at least one byte per descriptor, got " +
                                std::to_string(bytes));
  }
  if (!(ratio > 0.0 && ratio <= 1.0)) {
    throw std::invalid_argument("ratio: expected a value in (0, 1], got " + std::to_string(ratio));
  }
  HammingMatches out;
  if (num_train < 2) return out;
  // Kept query per train row (-1: none yet) and its distance.
  std::vector<int> owner(num_train, -1), owner_distance(num_train, INT_MAX);
  std::vector<TwoNearest> nearest(num_query);
  AllNearestTwo(query, num_query, train, num_train, bytes, nearest.data());
  for (int i = 0; i < num_query; ++i) {
    const TwoNearest& n = nearest[i];
    if (!(n.best < ratio * n.second)) continue;  // also drops a tie for the best
    if (n.best < owner_distance[n.index]) {
      owner[n.index] = i;
      owner_distance[n.index] = n.best;
    }
  }
  std::vector<int> train_of(num_query, -1);
  for (int j = 0; j < num_train; ++j) {
    if (owner[j] >= 0) train_of[owner[j]] = j;
  }
  for (int i = 0; i < num_query; ++i) {
    if (train_of[i] < 0) continue;
    out.query.push_back(i);
    out.train.push_back(train_of[i]);
    out.distance.push_back(owner_distance[train_of[i]]);
  }
  return out;
}

}  // namespace fusedmosaic
