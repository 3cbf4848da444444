#include "fusedmosaic/registration/hamming_match.h"

#include <algorithm>
#include <climits>
#include <cmath>
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

// Train keypoints bucketed in square cells at least the search radius wide (compressed rows:
// the train rows of cell c are rows[start[c] .. start[c + 1])), for the guided search.
struct Grid {
  double min_x = 0.0, min_y = 0.0, cell = 1.0, radius = 0.0;
  int nx = 0, ny = 0;
  std::vector<int> start, rows;
  const double* xy = nullptr;
};

Grid MakeGrid(const double* xy, int n, double radius) {
  Grid g;
  g.xy = xy;
  g.radius = radius;
  double min_x = HUGE_VAL, min_y = HUGE_VAL, max_x = -HUGE_VAL, max_y = -HUGE_VAL;
  for (int j = 0; j < n; ++j) {
    const double x = xy[2 * j], y = xy[2 * j + 1];
    if (!std::isfinite(x) || !std::isfinite(y)) continue;
    min_x = std::min(min_x, x), max_x = std::max(max_x, x);
    min_y = std::min(min_y, y), max_y = std::max(max_y, y);
  }
  if (!(min_x <= max_x)) return g;  // no finite train keypoint: an empty grid
  // Cells of the radius, widened so that there are at most ~4 per train keypoint.
  const double w = max_x - min_x, h = max_y - min_y;
  if (!std::isfinite(w) || !std::isfinite(h)) {
    throw std::invalid_argument(
        "train_xy: the keypoints span more than a double holds (coordinates near 1e308)");
  }
  g.cell = std::max(radius, std::sqrt(w * h / (4.0 * n + 16.0)));
  g.cell = std::max({g.cell, w / 4096.0, h / 4096.0});
  g.min_x = min_x, g.min_y = min_y;
  g.nx = static_cast<int>(w / g.cell) + 1;
  g.ny = static_cast<int>(h / g.cell) + 1;
  std::vector<int> cell_of(n, -1);
  g.start.assign(static_cast<size_t>(g.nx) * g.ny + 1, 0);
  for (int j = 0; j < n; ++j) {
    const double x = xy[2 * j], y = xy[2 * j + 1];
    if (!std::isfinite(x) || !std::isfinite(y)) continue;
    const int cx = std::min(g.nx - 1, static_cast<int>((x - min_x) / g.cell));
    const int cy = std::min(g.ny - 1, static_cast<int>((y - min_y) / g.cell));
    cell_of[j] = cy * g.nx + cx;
    ++g.start[cell_of[j] + 1];
  }
  for (size_t c = 1; c < g.start.size(); ++c) g.start[c] += g.start[c - 1];
  g.rows.resize(g.start.back());
  std::vector<int> fill(g.start.begin(), g.start.end() - 1);
  for (int j = 0; j < n; ++j) {
    if (cell_of[j] >= 0) g.rows[fill[cell_of[j]]++] = j;  // ascending rows within a cell
  }
  return g;
}

// Cell index range [lo, hi] covering coordinate v +- radius, clamped to the grid; false if the
// interval misses the grid.
inline bool CellRange(double v, double origin, double cell, double radius, int count, int* lo,
                      int* hi) {
  const double a = std::floor((v - radius - origin) / cell);
  const double b = std::floor((v + radius - origin) / cell);
  if (b < 0.0 || a > count - 1) return false;
  *lo = a < 0.0 ? 0 : static_cast<int>(a);
  *hi = b > count - 1 ? count - 1 : static_cast<int>(b);
  return true;
}

// One matching problem: brute force over every train row, or (grid set) guided.
struct Search {
  const std::uint8_t* query;
  int num_query;
  const std::uint8_t* train;
  int num_train;
  int bytes;
  const double* query_xy = nullptr;  // guided only
  const Grid* grid = nullptr;
};

// Hamming distance of two descriptors. Words: descriptor length in 64-bit words when fixed at
// compile time (ORB: 4), 0 for any length. This and the helpers below are always inlined, so
// that the popcount build further down compiles all of them with the popcount instruction.
template <int Words>
__attribute__((always_inline)) inline int Distance(const std::uint8_t* q, const std::uint8_t* t,
                                                   int bytes) {
  const int words = Words > 0 ? Words : bytes / 8;
  int d = 0;
  for (int w = 0; w < words; ++w) {
    std::uint64_t a, b;
    std::memcpy(&a, q + 8 * w, 8);
    std::memcpy(&b, t + 8 * w, 8);
    d += __builtin_popcountll(a ^ b);
  }
  if constexpr (Words == 0) {
    for (int k = 8 * words; k < bytes; ++k) d += __builtin_popcount(q[k] ^ t[k]);
  }
  return d;
}

// The two nearest train rows of query i: all rows, or those within the grid's radius of the
// query's predicted position.
template <int Words>
__attribute__((always_inline)) inline TwoNearest NearestTwo(const Search& s, int i) {
  TwoNearest out;
  const std::uint8_t* q = s.query + static_cast<size_t>(i) * s.bytes;
  if (s.grid == nullptr) {
    for (int j = 0; j < s.num_train; ++j) {
      out.Add(Distance<Words>(q, s.train + static_cast<size_t>(j) * s.bytes, s.bytes), j);
    }
    return out;
  }
  const Grid& g = *s.grid;
  const double px = s.query_xy[2 * i], py = s.query_xy[2 * i + 1];
  int x0, x1, y0, y1;
  if (g.nx == 0 || !std::isfinite(px) || !std::isfinite(py) ||
      !CellRange(px, g.min_x, g.cell, g.radius, g.nx, &x0, &x1) ||
      !CellRange(py, g.min_y, g.cell, g.radius, g.ny, &y0, &y1)) {
    return out;
  }
  const double r2 = g.radius * g.radius;
  for (int cy = y0; cy <= y1; ++cy) {
    for (int cx = x0; cx <= x1; ++cx) {
      const int c = cy * g.nx + cx;
      for (int k = g.start[c]; k < g.start[c + 1]; ++k) {
        const int j = g.rows[k];
        const double dx = g.xy[2 * j] - px, dy = g.xy[2 * j + 1] - py;
        if (dx * dx + dy * dy > r2) continue;
        out.Add(Distance<Words>(q, s.train + static_cast<size_t>(j) * s.bytes, s.bytes), j);
      }
    }
  }
  return out;
}

__attribute__((always_inline)) inline void NearestTwoOfEach(const Search& s, TwoNearest* out) {
  for (int i = 0; i < s.num_query; ++i) {
    out[i] = s.bytes == 32 ? NearestTwo<4>(s, i) : NearestTwo<0>(s, i);
  }
}

// Built twice: with the popcount instruction (NearestTwoOfEach inlined into a popcnt-target
// function), picked at run time on CPUs that have it (every x86-64 since ~2008), and without (a
// bit-counting routine), so the module never executes an instruction the CPU lacks.
#if defined(__x86_64__) && defined(__GNUC__)
#define FUSEDMOSAIC_HAVE_POPCNT_CLONE 1
__attribute__((target("popcnt"))) void NearestTwoOfEachPopcnt(const Search& s, TwoNearest* out) {
  NearestTwoOfEach(s, out);
}
#endif

void AllNearestTwo(const Search& s, TwoNearest* out) {
#ifdef FUSEDMOSAIC_HAVE_POPCNT_CLONE
  if (__builtin_cpu_supports("popcnt")) {
    NearestTwoOfEachPopcnt(s, out);
    return;
  }
#endif
  NearestTwoOfEach(s, out);
}

void CheckArguments(int bytes, double ratio) {
  if (bytes <= 0) {
    throw std::invalid_argument("descriptors: expected at least one byte per descriptor, got " +
                                std::to_string(bytes));
  }
  if (!(ratio > 0.0 && ratio <= 1.0)) {
    throw std::invalid_argument("ratio: expected a value in (0, 1], got " + std::to_string(ratio));
  }
}

// Ratio test (a query with a single candidate: kept if within max_distance >= 0), then one query
// per train row, the nearest (the first in query order on a tie); ascending query order.
HammingMatches Select(const Search& s, double ratio, int max_distance) {
  HammingMatches out;
  // Kept query per train row (-1: none yet) and its distance.
  std::vector<int> owner(s.num_train, -1), owner_distance(s.num_train, INT_MAX);
  std::vector<TwoNearest> nearest(s.num_query);
  AllNearestTwo(s, nearest.data());
  for (int i = 0; i < s.num_query; ++i) {
    const TwoNearest& n = nearest[i];
    if (n.index < 0) continue;
    const bool kept = n.second == INT_MAX ? max_distance >= 0 && n.best <= max_distance
                                          : n.best < ratio * n.second;  // drops a tied best
    if (!kept) continue;
    if (n.best < owner_distance[n.index]) {
      owner[n.index] = i;
      owner_distance[n.index] = n.best;
    }
  }
  std::vector<int> train_of(s.num_query, -1);
  for (int j = 0; j < s.num_train; ++j) {
    if (owner[j] >= 0) train_of[owner[j]] = j;
  }
  for (int i = 0; i < s.num_query; ++i) {
    if (train_of[i] < 0) continue;
    out.query.push_back(i);
    out.train.push_back(train_of[i]);
    out.distance.push_back(owner_distance[train_of[i]]);
  }
  return out;
}

}  // namespace

HammingMatches MatchHammingRatio(const std::uint8_t* query, int num_query,
                                 const std::uint8_t* train, int num_train, int bytes,
                                 double ratio) {
  CheckArguments(bytes, ratio);
  if (num_train < 2) return {};
  return Select(Search{query, num_query, train, num_train, bytes}, ratio, -1);
}

HammingMatches MatchHammingGuided(const std::uint8_t* query, const double* query_xy,
                                  int num_query, const std::uint8_t* train,
                                  const double* train_xy, int num_train, int bytes,
                                  double radius, double ratio, int max_distance) {
  CheckArguments(bytes, ratio);
  if (!(radius > 0.0 && std::isfinite(radius))) {
    throw std::invalid_argument("radius: expected a positive finite number of pixels, got " +
                                std::to_string(radius));
  }
  const Grid grid = MakeGrid(train_xy, num_train, radius);
  Search s{query, num_query, train, num_train, bytes, query_xy, &grid};
  return Select(s, ratio, max_distance);
}

}  // namespace fusedmosaic
