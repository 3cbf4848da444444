#include "fusedmosaic/io/crc64.h"

#include <array>

namespace fusedmosaic::io {
namespace {

constexpr std::uint64_t kPolynomial = 0x42F0E1EBA9EA3693ULL;

// tables[k][b]: the CRC of byte b followed by k zero bytes (tables[0] the byte-wise table).
struct Tables {
  std::array<std::array<std::uint64_t, 256>, 8> t{};
  constexpr Tables() {
    for (int b = 0; b < 256; ++b) {
      std::uint64_t crc = static_cast<std::uint64_t>(b) << 56;
      for (int bit = 0; bit < 8; ++bit) {
        crc = (crc & (1ULL << 63)) ? (crc << 1) ^ kPolynomial : crc << 1;
      }
      t[0][b] = crc;
    }
    for (int k = 1; k < 8; ++k) {
      for (int b = 0; b < 256; ++b) {
        t[k][b] = (t[k - 1][b] << 8) ^ t[0][t[k - 1][b] >> 56];
      }
    }
  }
};

constexpr Tables kTables;

}  // namespace

std::uint64_t Crc64Ecma(const std::uint8_t* data, std::size_t size) {
  const auto& t = kTables.t;
  std::uint64_t crc = 0;
  std::size_t i = 0;
  for (; i + 8 <= size; i += 8) {
    std::uint64_t word = 0;  // the next eight bytes, big-endian (the first one highest)
    for (int j = 0; j < 8; ++j) word = (word << 8) | data[i + j];
    const std::uint64_t x = crc ^ word;
    crc = t[7][x >> 56] ^ t[6][(x >> 48) & 0xFF] ^ t[5][(x >> 40) & 0xFF] ^
          t[4][(x >> 32) & 0xFF] ^ t[3][(x >> 24) & 0xFF] ^ t[2][(x >> 16) & 0xFF] ^
          t[1][(x >> 8) & 0xFF] ^ t[0][x & 0xFF];
  }
  for (; i < size; ++i) crc = (crc << 8) ^ t[0][(crc >> 56) ^ data[i]];
  return crc;
}

}  // namespace fusedmosaic::io
