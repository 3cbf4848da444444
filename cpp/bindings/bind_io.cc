// Python bindings of cpp/fusedmosaic/io.
#include <Python.h>
#include <pybind11/pybind11.h>

#include <cstdint>

#include "bindings/bind.h"
#include "fusedmosaic/io/crc64.h"

namespace py = pybind11;

namespace fusedmosaic::bindings {

void BindIo(py::module_& m) {
  m.def(
      "crc64",
      [](const py::object& data) {
        // Any contiguous buffer (bytes, bytearray, memoryview, a C-contiguous array), read in
        // place; the GIL is released while it runs (io.igtl checks each IMAGE body on its
        // receiving thread, beside the live loop).
        Py_buffer view;
        if (PyObject_GetBuffer(data.ptr(), &view, PyBUF_SIMPLE) != 0) {
          throw py::error_already_set();
        }
        std::uint64_t crc = 0;
        {
          py::gil_scoped_release release;
          crc = io::Crc64Ecma(static_cast<const std::uint8_t*>(view.buf),
                              static_cast<std::size_t>(view.len));
        }
        PyBuffer_Release(&view);
        return crc;
      },
      py::arg("data"),
      "CRC-64/ECMA-182 of a contiguous buffer, OpenIGTLink's body check (polynomial "
      "0x42F0E1EBA9EA3693, MSB first, initial value 0, no final xor); the GIL released.");
}

}  // namespace fusedmosaic::bindings
