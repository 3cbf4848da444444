// Python bindings of cpp/fusedmosaic/registration.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <string>

#include "bindings/bind.h"
#include "fusedmosaic/registration/hamming_match.h"

namespace py = pybind11;
using namespace pybind11::literals;

namespace fusedmosaic::bindings {
namespace {

using Descriptors = py::array_t<std::uint8_t, py::array::c_style | py::array::forcecast>;

void CheckDescriptors(const Descriptors& d, const char* name) {
  if (d.ndim() != 2) {
    throw std::invalid_argument(std::string(name) + ": expected a 2-D (N, bytes) uint8 array, got " +
                                std::to_string(d.ndim()) + " dimension(s)");
  }
}

py::array_t<int> ToArray(const std::vector<int>& v) {
  py::array_t<int> out(static_cast<py::ssize_t>(v.size()));
  std::copy(v.begin(), v.end(), out.mutable_data());
  return out;
}

}  // namespace

void BindRegistration(py::module_& m) {
  m.def(
      "match_hamming",
      [](const Descriptors& query, const Descriptors& train, double ratio) {
        CheckDescriptors(query, "query");
        CheckDescriptors(train, "train");
        if (query.shape(1) != train.shape(1)) {
          throw std::invalid_argument("query and train descriptors differ in length: " +
                                      std::to_string(query.shape(1)) + " and " +
                                      std::to_string(train.shape(1)) + " bytes");
        }
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
}

}  // namespace fusedmosaic::bindings
