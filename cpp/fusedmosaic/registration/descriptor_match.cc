#include "fusedmosaic/registration/descriptor_match.h"
#include "fusedmosaic/util/format.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

namespace fusedmosaic {
namespace {

// Distance: int Hamming bits, or float squared L2.
template <typename Distance>
struct TwoNearest {
  static constexpr Distance kNone = std::numeric_limits<Distance>::max();
  Distance best = kNone, second = kNone;
  int index = -1;

  void Add(Distance d, int j) {
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

// One matching problem over descriptors of element type T, `length` elements each: brute force
// over every train row, or (grid set) guided.
template <typename T>
struct Search {
  const T* query;
  int num_query;
  const T* train;
  int num_train;
  int length;
  const double* query_xy = nullptr;  // guided only
  const Grid* grid = nullptr;
  // Guided: a query with a single candidate in its radius takes as second nearest the nearest
  // of all the other train rows (the ratio test the exhaustive search would apply to it).
  bool lone_against_all = false;
};

// The two metrics. Compute<Fixed>: the distance of two descriptors, with the descriptor length
// fixed at compile time (Fixed > 0: ORB's 4 64-bit words, SIFT's 128 floats) or any (0). These
// and the helpers below are always inlined, so that the instruction-set builds further down
// compile all of them for that instruction set.
struct Hamming {
  using Element = std::uint8_t;
  using Distance = int;  // bits
  static constexpr int kFixed = 4;  // 32-byte descriptors (ORB), in 64-bit words

  static bool IsFixed(int length) { return length == 8 * kFixed; }

  template <int Fixed>
  __attribute__((always_inline)) static inline int Compute(const std::uint8_t* q,
                                                           const std::uint8_t* t, int bytes) {
    const int words = Fixed > 0 ? Fixed : bytes / 8;
    int d = 0;
    for (int w = 0; w < words; ++w) {
      std::uint64_t a, b;
      std::memcpy(&a, q + 8 * w, 8);
      std::memcpy(&b, t + 8 * w, 8);
      d += __builtin_popcountll(a ^ b);
    }
    if constexpr (Fixed == 0) {
      for (int k = 8 * words; k < bytes; ++k) d += __builtin_popcount(q[k] ^ t[k]);
    }
    return d;
  }
};

struct L2 {
  using Element = float;
  using Distance = float;  // squared Euclidean distance
  static constexpr int kFixed = 128;  // SIFT

  static bool IsFixed(int length) { return length == kFixed; }

  // Eight independent partial sums (lane u sums elements u, u + 8, ...), so that the loop
  // vectorises without reordering any sum: every build gives the same bits.
  template <int Fixed>
  __attribute__((always_inline)) static inline float Compute(const float* q, const float* t,
                                                             int dims) {
    const int n = Fixed > 0 ? Fixed : dims;
    float acc[8] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    int k = 0;
    for (; k + 8 <= n; k += 8) {
      for (int u = 0; u < 8; ++u) {
        const float d = q[k + u] - t[k + u];
        acc[u] += d * d;
      }
    }
    float sum = ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
    for (; k < n; ++k) {
      const float d = q[k] - t[k];
      sum += d * d;
    }
    return sum;
  }
};

// The two nearest train rows of query i: all rows, or those within the grid's radius of the
// query's predicted position.
template <typename Metric, int Fixed>
__attribute__((always_inline)) inline TwoNearest<typename Metric::Distance> NearestTwo(
    const Search<typename Metric::Element>& s, int i) {
  TwoNearest<typename Metric::Distance> out;
  const auto* q = s.query + static_cast<size_t>(i) * s.length;
  if (s.grid == nullptr) {
    for (int j = 0; j < s.num_train; ++j) {
      out.Add(Metric::template Compute<Fixed>(q, s.train + static_cast<size_t>(j) * s.length,
                                              s.length),
              j);
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
        out.Add(Metric::template Compute<Fixed>(q, s.train + static_cast<size_t>(j) * s.length,
                                                s.length),
                j);
      }
    }
  }
  if (s.lone_against_all && out.index >= 0 && out.second == out.kNone) {
    for (int j = 0; j < s.num_train; ++j) {
      if (j == out.index) continue;
      out.second = std::min(out.second, Metric::template Compute<Fixed>(
                                            q, s.train + static_cast<size_t>(j) * s.length,
                                            s.length));
    }
  }
  return out;
}

template <typename Metric>
__attribute__((always_inline)) inline void NearestTwoOfEach(
    const Search<typename Metric::Element>& s, TwoNearest<typename Metric::Distance>* out) {
  const bool fixed = Metric::IsFixed(s.length);
  for (int i = 0; i < s.num_query; ++i) {
    out[i] = fixed ? NearestTwo<Metric, Metric::kFixed>(s, i) : NearestTwo<Metric, 0>(s, i);
  }
}

// Each metric is built twice: for an instruction set that speeds it up (Hamming: popcount,
// every x86-64 since ~2008; L2: AVX's 8-float vectors, no FMA so that the sums stay those of the
// baseline build), picked at run time on CPUs that have it, and for the baseline, so the module
// never executes an instruction the CPU lacks.
#if defined(__x86_64__) && defined(__GNUC__)
#define FUSEDMOSAIC_HAVE_X86_CLONES 1
__attribute__((target("popcnt"))) void NearestTwoOfEachPopcnt(const Search<std::uint8_t>& s,
                                                              TwoNearest<int>* out) {
  NearestTwoOfEach<Hamming>(s, out);
}
__attribute__((target("avx"))) void NearestTwoOfEachAvx(const Search<float>& s,
                                                        TwoNearest<float>* out) {
  NearestTwoOfEach<L2>(s, out);
}
#endif

void AllNearestTwo(const Search<std::uint8_t>& s, TwoNearest<int>* out) {
#ifdef FUSEDMOSAIC_HAVE_X86_CLONES
  if (__builtin_cpu_supports("popcnt")) {
    NearestTwoOfEachPopcnt(s, out);
    return;
  }
#endif
  NearestTwoOfEach<Hamming>(s, out);
}

void AllNearestTwo(const Search<float>& s, TwoNearest<float>* out) {
#ifdef FUSEDMOSAIC_HAVE_X86_CLONES
  if (__builtin_cpu_supports("avx")) {
    NearestTwoOfEachAvx(s, out);
    return;
  }
#endif
  NearestTwoOfEach<L2>(s, out);
}

void CheckArguments(int length, double ratio, const char* unit) {
  if (length <= 0) {
    throw std::invalid_argument(std::string("descriptors: expected at least one ") + unit +
                                " per descriptor, got " + std::to_string(length));
  }
  if (!(ratio > 0.0 && ratio <= 1.0)) {
    throw std::invalid_argument("ratio: expected a value in (0, 1], got " + FormatDouble(ratio));
  }
}

void CheckRadius(double radius) {
  if (!(radius > 0.0 && std::isfinite(radius))) {
    throw std::invalid_argument("radius: expected a positive finite number of pixels, got " +
                                FormatDouble(radius));
  }
}

// Ratio test (best < factor * second), then one query per train row, the nearest (the first in
// query order on a tie); ascending query order. Distances in the metric's units. A query whose
// search found a single candidate and no second is kept if best <= max_distance; with
// max_distance < 0 the guided search (Search::lone_against_all) has already filled in `second`
// from all the other train rows, so only a train set of one row leaves it unset: never kept.
template <typename Metric, typename T = typename Metric::Element,
          typename D = typename Metric::Distance>
Matches<D> Select(const Search<T>& s, double factor, D max_distance) {
  Matches<D> out;
  // Kept query per train row (-1: none yet) and its distance.
  std::vector<int> owner(s.num_train, -1);
  std::vector<D> owner_distance(s.num_train, TwoNearest<D>::kNone);
  std::vector<TwoNearest<D>> nearest(s.num_query);
  AllNearestTwo(s, nearest.data());
  for (int i = 0; i < s.num_query; ++i) {
    const TwoNearest<D>& n = nearest[i];
    if (n.index < 0) continue;
    const bool kept = n.second == TwoNearest<D>::kNone
                          ? max_distance >= 0 && n.best <= max_distance
                          : n.best < factor * n.second;  // drops a tied best
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
  CheckArguments(bytes, ratio, "byte");
  if (num_train < 2) return {};
  return Select<Hamming>(Search<std::uint8_t>{query, num_query, train, num_train, bytes}, ratio,
                         -1);
}

HammingMatches MatchHammingGuided(const std::uint8_t* query, const double* query_xy,
                                  int num_query, const std::uint8_t* train,
                                  const double* train_xy, int num_train, int bytes,
                                  double radius, double ratio, int max_distance) {
  CheckArguments(bytes, ratio, "byte");
  CheckRadius(radius);
  const Grid grid = MakeGrid(train_xy, num_train, radius);
  Search<std::uint8_t> s{query, num_query, train, num_train, bytes, query_xy, &grid,
                         max_distance < 0};
  return Select<Hamming>(s, ratio, max_distance);
}

L2Matches MatchL2Guided(const float* query, const double* query_xy, int num_query,
                        const float* train, const double* train_xy, int num_train, int dims,
                        double radius, double ratio, double max_distance) {
  CheckArguments(dims, ratio, "float");
  CheckRadius(radius);
  if (std::isnan(max_distance)) {
    throw std::invalid_argument("max_distance: expected a number (< 0: never), got nan");
  }
  const Grid grid = MakeGrid(train_xy, num_train, radius);
  Search<float> s{query, num_query, train, num_train, dims, query_xy, &grid, max_distance < 0.0};
  // Squared distances: the ratio test d1 < ratio d2 is d1^2 < ratio^2 d2^2.
  const float max_squared =
      max_distance < 0.0 ? -1.0f : static_cast<float>(std::min(max_distance * max_distance, 1e38));
  L2Matches out = Select<L2>(s, ratio * ratio, max_squared);
  for (float& d : out.distance) d = std::sqrt(d);
  return out;
}

}  // namespace fusedmosaic
