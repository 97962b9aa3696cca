// Checksums used by the device codecs and the ParamStore.
// - CRC-16-CCITT (polynomial 0x1021, init 0xFFFF, MSB first, no reflection, no final XOR): the
//   ADS131M0x output/input CRC (TI datasheet SBAS788 "SPI CRC", TI SBAA106 "CRC-16-CCITT 1021h").
//   Check value for "123456789" is 0x29B1 (CRC-16/CCITT-FALSE).
// - CRC-32 (IEEE 802.3, reflected polynomial 0xEDB88320, init and final XOR 0xFFFFFFFF).
//   Check value for "123456789" is 0xCBF43926.
// - NMEA-style XOR checksum (XOR of all bytes between '$' and '*').
// Bitwise implementations: small code, no tables (MCU flash), fast enough for <100 bytes per frame.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

namespace magvec::drivers {

constexpr std::uint16_t crc16_ccitt(std::span<const std::uint8_t> data,
                                    std::uint16_t crc = 0xFFFF) noexcept {
  // The shifts are done on an unsigned 32-bit copy: shifting the uint16_t itself promotes it to
  // (signed) int, and GCC's -fsanitize=shift then reports the int-to-unsigned conversion of the
  // result under -Wsign-conversion.
  std::uint32_t c = crc;
  for (const std::uint8_t byte : data) {
    c ^= static_cast<std::uint32_t>(byte) << 8u;
    for (int bit = 0; bit < 8; ++bit)
      c = (c & 0x8000u) != 0 ? ((c << 1u) ^ 0x1021u) & 0xFFFFu : (c << 1u) & 0xFFFFu;
  }
  return static_cast<std::uint16_t>(c);
}

constexpr std::uint32_t crc32_update(std::uint32_t state,
                                     std::span<const std::uint8_t> data) noexcept {
  for (const std::uint8_t byte : data) {
    state ^= byte;
    for (int bit = 0; bit < 8; ++bit) {
      state = (state & 1u) != 0 ? (state >> 1) ^ 0xEDB88320u : state >> 1;
    }
  }
  return state;
}
inline constexpr std::uint32_t kCrc32Init = 0xFFFFFFFFu;
constexpr std::uint32_t crc32_final(std::uint32_t state) noexcept {
  return state ^ 0xFFFFFFFFu;
}
constexpr std::uint32_t crc32(std::span<const std::uint8_t> data) noexcept {
  return crc32_final(crc32_update(kCrc32Init, data));
}

constexpr std::uint8_t xor_checksum(std::span<const std::uint8_t> data) noexcept {
  std::uint8_t x = 0;
  for (const std::uint8_t byte : data)
    x = static_cast<std::uint8_t>(x ^ byte);
  return x;
}

}  // namespace magvec::drivers
