// Python bindings of cpp/fusedmosaic/registration.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <string>
#include <type_traits>

#include "bindings/bind.h"
#include "fusedmosaic/registration/descriptor_match.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

using Descriptors = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>;
using FloatDescriptors = py::array_t<float, py::array::c_style | py::array::forcecast>;

template <typename T>
const char* Layout() {
  return std::is_same_v<T, float> ? "(N, dims) float32" : "(N, bytes) uint8";
}
template <typename T>
const char* Unit() {
  return std::is_same_v<T, float> ? " floats" : " bytes";
}

template <typename T>
void CheckDescriptors(const py::array_t<T, py::array::c_style | py::array::forcecast>& d,
                      const char* name) {
  if (d.ndim() != 2) {
    throw std::invalid_argument(std::string(name) + ": expected a 2-D " + Layout<T>() +
                                " array, got " + std::to_string(d.ndim()) + " dimension(s)");
  }
}

using Points = py::array_t<double, py::array::c_style | py::array::forcecast>;

template <typename T>
void CheckDescriptorLengths(const py::array_t<T, py::array::c_style | py::array::forcecast>& query,
                            const py::array_t<T, py::array::c_style | py::array::forcecast>& train) {
  if (query.shape(1) != train.shape(1)) {
    throw std::invalid_argument("query and train descriptors differ in length: " +
                                std::to_string(query.shape(1)) + " and " +
                                std::to_string(train.shape(1)) + Unit<T>());
  }
}

void CheckPoints(const Points& xy, const py::array& d, const char* name, const char* of) {
  if (xy.ndim() != 2 || xy.shape(1) != 2 || xy.shape(0) != d.shape(0)) {
    std::string shape;
    for (py::ssize_t i = 0; i < xy.ndim(); ++i) {
      shape += (i ? ", " : "") + std::to_string(xy.shape(i));
    }
    throw std::invalid_argument(std::string(name) + ": expected (" + std::to_string(d.shape(0)) +
                                ", 2) positions, one per " + of + " descriptor, got (" + shape +
                                ")");
  }
}

template <typename T>
py::array_t<T> ToArray(const std::vector<T>& v) {
  py::array_t<T> out(static_cast<py::ssize_t>(v.size()));
  std::copy(v.begin(), v.end(), out.mutable_data());
  return out;
}

// The guided matchers' shared binding: shape checks, the search with the GIL released (`match`
// takes the row counts and the descriptor length), (query, train, distance) arrays.
template <typename T, typename Match>
py::tuple GuidedMatches(const py::array_t<T, py::array::c_style | py::array::forcecast>& query,
                        const Points& query_xy,
                        const py::array_t<T, py::array::c_style | py::array::forcecast>& train,
                        const Points& train_xy, Match match) {
  CheckDescriptors(query, "query");
  CheckDescriptors(train, "train");
  CheckDescriptorLengths(query, train);
  CheckPoints(query_xy, query, "query_xy", "query");
  CheckPoints(train_xy, train, "train_xy", "train");
  decltype(match(0, 0, 0)) found;
  {
    py::gil_scoped_release release;
    found = match(static_cast<int>(query.shape(0)), static_cast<int>(train.shape(0)),
                  static_cast<int>(query.shape(1)));
  }
  return py::make_tuple(ToArray(found.query), ToArray(found.train), ToArray(found.distance));
}

}  // namespace

void BindRegistration(py::module_& m) {
  m.def(
      "match_hamming",
      [](const Descriptors& query, const Descriptors& train, double ratio) {
        CheckDescriptors(query, "query");
        CheckDescriptors(train, "train");
        CheckDescriptorLengths(query, train);
        HammingMatches found;
        {
          py::gil_scoped_release release;
          found = MatchHammingRatio(query.data(), static_cast<int>(query.shape(0)), train.data(),
                                    static_cast<int>(train.shape(0)),
                                    static_cast<int>(query.shape(1)), ratio);
        }
        return py::make_tuple(ToArray(found.query), ToArray(found.train),
                              ToArray(found.distance));
      },
      "query"_a, "train"_a, "ratio"_a = 0.8,
      R"doc(Exact Hamming nearest neighbours of binary descriptors, ratio test, one-to-one.

query : (Nq, B) uint8, train : (Nt, B) uint8 (e.g. ORB, B = 32); ratio in (0, 1].
Returns (query_idx, train_idx, distance), int arrays of the kept matches in ascending query
order: a query is kept if its nearest train descriptor is nearer than ratio x the second
nearest, and of the queries kept for one train descriptor only the nearest (the first on a tie).
The same matches as cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query, train, k=2) with these two
filters; computed with the CPU's popcount, the GIL released.)doc");

  m.def(
      "match_hamming_guided",
      [](const Descriptors& query, const Points& query_xy, const Descriptors& train,
         const Points& train_xy, double radius, double ratio, int max_distance) {
        return GuidedMatches(query, query_xy, train, train_xy, [&](int nq, int nt, int bytes) {
          return MatchHammingGuided(query.data(), query_xy.data(), nq, train.data(),
                                    train_xy.data(), nt, bytes, radius, ratio, max_distance);
        });
      },
      "query"_a, "query_xy"_a, "train"_a, "train_xy"_a, "radius"_a, "ratio"_a = 0.8,
      "max_distance"_a = -1,
      R"doc(match_hamming restricted to candidates near a predicted position (guided matching).

query_xy : (Nq, 2) where each query keypoint is predicted in the train image (e.g. through a
homography from a motion model; a non-finite row: that query is not matched); train_xy :
(Nt, 2) the train keypoints. Only train descriptors within `radius` px of the prediction are
compared; the ratio test uses the two nearest of those. A query with a single candidate is kept
if its distance is at most max_distance bits or, with max_distance < 0 (default), if it passes
the ratio test against the nearest of all the other train descriptors. Same output as
match_hamming. Cost grows with the candidates per query (a grid of radius-sized cells), not
with Nt (except for lone candidates under max_distance < 0).)doc");

  m.def(
      "match_l2_guided",
      [](const FloatDescriptors& query, const Points& query_xy, const FloatDescriptors& train,
         const Points& train_xy, double radius, double ratio, double max_distance) {
        return GuidedMatches(query, query_xy, train, train_xy, [&](int nq, int nt, int dims) {
          return MatchL2Guided(query.data(), query_xy.data(), nq, train.data(), train_xy.data(),
                               nt, dims, radius, ratio, max_distance);
        });
      },
      "query"_a, "query_xy"_a, "train"_a, "train_xy"_a, "radius"_a, "ratio"_a = 0.8,
      "max_distance"_a = -1.0,
      R"doc(match_hamming_guided for float descriptors (SIFT) under the Euclidean distance.

query : (Nq, D) float32, train : (Nt, D) float32; query_xy : (Nq, 2) predicted positions in the
train image (a non-finite row: not matched), train_xy : (Nt, 2). Only train descriptors within
`radius` px of the prediction are compared; a query is kept if its nearest candidate is nearer
than ratio x the second nearest (Euclidean distances, as cv2.BFMatcher(cv2.NORM_L2)'s); a lone
candidate as in match_hamming_guided, max_distance in the same units; of the queries kept
for one train descriptor only the nearest. Returns (query_idx, train_idx, distance): int, int,
float32 arrays in ascending query order. A descriptor with a non-finite element matches nothing.)doc");
}

}  // namespace fusedmosaic::bindings
