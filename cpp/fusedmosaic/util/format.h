// Number formatting for error messages.
#pragma once

#include <cstdio>
#include <string>

namespace fusedmosaic {

// A double as printf's %g prints it: std::to_string's fixed 6 decimals print -1e-9 as
// "-0.000000" and 1e20 with 20 digits, so a message would misreport the value it refuses.
inline std::string FormatDouble(double value) {
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%g", value);
  return buffer;
}

}  // namespace fusedmosaic
