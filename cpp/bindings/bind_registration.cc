// Python bindings of cpp/fusedmosaic/registration.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <limits>
#include <string>
#include <type_traits>

#include "bindings/bind.h"
#include "fusedmosaic/registration/descriptor_match.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

using Descriptors = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>;
using Points = py::array_t<double, py::array::c_style | py::array::forcecast>;

template <typename T>
const char* Layout() {
  return std::is_same_v<T, float> ? "(N, dims) float32" : "(N, bytes) uint8";
}
template <typename T>
const char* Unit() {
  return std::is_same_v<T, float> ? " floats" : " bytes";
}

// Checks descriptors as given, before any conversion, and converts them. Binary descriptors
// must be uint8: a cast (forcecast) wrapped ints modulo 256 (+256: "exact" matches at distance
// 0) and truncated float descriptors to 0, matching nothing, with no error. Float descriptors
// are converted to float32 (the L2 matcher's type). The matchers count rows and lengths in int:
// larger arrays are refused here, before a copy of them is made.
template <typename T>
py::array_t<T, py::array::c_style | py::array::forcecast> ToDescriptors(const py::object& given,
                                                                       const char* name) {
  const py::array d = py::array::ensure(given);  // numpy's conversion of a list, as np.asarray
  if (!d || d.ndim() != 2) {
    throw std::invalid_argument(std::string(name) + ": expected a 2-D " + Layout<T>() +
                                " array, got " +
                                (d ? std::to_string(d.ndim()) + " dimension(s)"
                                   : py::str(py::type::of(given)).cast<std::string>()));
  }
  if constexpr (std::is_same_v<T, std::uint8_t>) {
    if (!(d.dtype().kind() == 'u' && d.dtype().itemsize() == 1)) {
      throw std::invalid_argument(std::string(name) + ": expected uint8 binary descriptors, got " +
                                  py::str(d.dtype()).cast<std::string>());
    }
  }
  for (int axis = 0; axis < 2; ++axis) {
    if (d.shape(axis) > std::numeric_limits<int>::max()) {
      throw std::invalid_argument(std::string(name) + ": " + std::to_string(d.shape(axis)) +
                                  (axis == 0 ? " rows" : Unit<T>()) + " exceed the limit of " +
                                  std::to_string(std::numeric_limits<int>::max()));
    }
  }
  return py::array_t<T, py::array::c_style | py::array::forcecast>::ensure(d);
}

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
                                (xy.ndim() == 1 ? ",)" : ")"));
  }
}

template <typename T>
py::array_t<T> ToArray(const std::vector<T>& v) {
  py::array_t<T> out(static_cast<py::ssize_t>(v.size()));
  std::copy(v.begin(), v.end(), out.mutable_data());
  return out;
}

// The guided matchers' shared binding: shape checks, the search with the GIL released (`match`
// takes the descriptors, the row counts and the descriptor length), (query, train, distance)
// arrays.
template <typename T, typename Match>
py::tuple GuidedMatches(const py::object& query_array, const Points& query_xy,
                        const py::object& train_array, const Points& train_xy, Match match) {
  const auto query = ToDescriptors<T>(query_array, "query");
  const auto train = ToDescriptors<T>(train_array, "train");
  CheckDescriptorLengths(query, train);
  CheckPoints(query_xy, query, "query_xy", "query");
  CheckPoints(train_xy, train, "train_xy", "train");
  decltype(match(query.data(), train.data(), 0, 0, 0)) found;
  {
    py::gil_scoped_release release;
    found = match(query.data(), train.data(), static_cast<int>(query.shape(0)),
                  static_cast<int>(train.shape(0)), static_cast<int>(query.shape(1)));
  }
  return py::make_tuple(ToArray(found.query), ToArray(found.train), ToArray(found.distance));
}

}  // namespace

void BindRegistration(py::module_& m) {
  m.def(
      "match_hamming",
      [](const py::object& query_array, const py::object& train_array, double ratio) {
        const Descriptors query = ToDescriptors<std::uint8_t>(query_array, "query");
        const Descriptors train = ToDescriptors<std::uint8_t>(train_array, "train");
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

query : (Nq, B) uint8, train : (Nt, B) uint8 (e.g. ORB, B = 32; another dtype: ValueError);
ratio in (0, 1].
Returns (query_idx, train_idx, distance), int32 arrays of the kept matches in ascending query
order: a query is kept if its nearest train descriptor is nearer than ratio x the second
nearest, and of the queries kept for one train descriptor only the nearest (the first on a tie).
The same matches as cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(query, train, k=2) with these two
filters; computed with the CPU's popcount, the GIL released.)doc");

  m.def(
      "match_hamming_guided",
      [](const py::object& query, const Points& query_xy, const py::object& train,
         const Points& train_xy, double radius, double ratio, int max_distance) {
        return GuidedMatches<std::uint8_t>(
            query, query_xy, train, train_xy,
            [&](const std::uint8_t* q, const std::uint8_t* t, int nq, int nt, int bytes) {
              return MatchHammingGuided(q, query_xy.data(), nq, t, train_xy.data(), nt, bytes,
                                        radius, ratio, max_distance);
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
      [](const py::object& query, const Points& query_xy, const py::object& train,
         const Points& train_xy, double radius, double ratio, double max_distance) {
        return GuidedMatches<float>(
            query, query_xy, train, train_xy,
            [&](const float* q, const float* t, int nq, int nt, int dims) {
              return MatchL2Guided(q, query_xy.data(), nq, t, train_xy.data(), nt, dims, radius,
                                   ratio, max_distance);
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
