// The ParamStore record of FlashParamStore (the MCU's persisted calibration), little endian:
//   off 0  u32 magic 'MVPS' (0x5350564D)
//   off 4  u16 version (1)
//   off 6  u16 header size (20)
//   off 8  u32 sequence number (serial-number arithmetic, newest wins)
//   off 12 u32 payload length
//   off 16 u32 CRC-32 (IEEE) over bytes 4..15 and the payload
//   off 20 payload
// Header-only, no heap: used on the MCU and on Linux.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/drivers/crc.hpp"

namespace magvec::drivers {

inline constexpr std::uint32_t kParamRecordMagic = 0x5350564Du;  // "MVPS" in little endian
inline constexpr std::uint16_t kParamRecordVersion = 1;
inline constexpr std::size_t kParamRecordHeaderSize = 20;

namespace param_record_detail {
constexpr std::uint32_t le32(const std::uint8_t* p) noexcept {
  return static_cast<std::uint32_t>(p[0]) | (static_cast<std::uint32_t>(p[1]) << 8) |
         (static_cast<std::uint32_t>(p[2]) << 16) | (static_cast<std::uint32_t>(p[3]) << 24);
}
constexpr std::uint16_t le16(const std::uint8_t* p) noexcept {
  return static_cast<std::uint16_t>(p[0] | (p[1] << 8));
}
constexpr void put32(std::uint8_t* p, std::uint32_t v) noexcept {
  for (int i = 0; i < 4; ++i)
    p[i] = static_cast<std::uint8_t>(v >> (8 * i));
}
constexpr void put16(std::uint8_t* p, std::uint16_t v) noexcept {
  p[0] = static_cast<std::uint8_t>(v);
  p[1] = static_cast<std::uint8_t>(v >> 8);
}
}  // namespace param_record_detail

// Serial-number comparison of sequence numbers: a is newer than b.
constexpr bool param_sequence_newer(std::uint32_t a, std::uint32_t b) noexcept {
  return static_cast<std::int32_t>(a - b) > 0;
}

struct ParamRecordHeader {
  bool valid{false};  // magic, version and header size match and length <= the caller's limit
  std::uint32_t sequence{0};
  std::uint32_t length{0};
  std::uint32_t crc{0};  // as stored
};

// Fills the 20-byte header for `payload` (magic included).
constexpr void encode_param_record_header(std::span<std::uint8_t, kParamRecordHeaderSize> h,
                                          std::uint32_t sequence,
                                          std::span<const std::uint8_t> payload) noexcept {
  using namespace param_record_detail;
  put32(h.data(), kParamRecordMagic);
  put16(h.data() + 4, kParamRecordVersion);
  put16(h.data() + 6, static_cast<std::uint16_t>(kParamRecordHeaderSize));
  put32(h.data() + 8, sequence);
  put32(h.data() + 12, static_cast<std::uint32_t>(payload.size()));
  const std::uint32_t crc =
      crc32_update(kCrc32Init, std::span<const std::uint8_t>(h.data() + 4, 12));
  put32(h.data() + 16, crc32_final(crc32_update(crc, payload)));
}

// Parses the header fields (no payload check).
constexpr ParamRecordHeader parse_param_record_header(
    std::span<const std::uint8_t, kParamRecordHeaderSize> h, std::size_t max_payload) noexcept {
  using namespace param_record_detail;
  ParamRecordHeader r;
  if (le32(h.data()) != kParamRecordMagic || le16(h.data() + 4) != kParamRecordVersion ||
      le16(h.data() + 6) != kParamRecordHeaderSize) {
    return r;
  }
  r.sequence = le32(h.data() + 8);
  r.length = le32(h.data() + 12);
  r.crc = le32(h.data() + 16);
  r.valid = r.length <= max_payload;
  return r;
}

// CRC state after the header fields; continue with crc32_update over the payload, then compare
// crc32_final(state) with ParamRecordHeader::crc.
constexpr std::uint32_t param_record_crc_start(
    std::span<const std::uint8_t, kParamRecordHeaderSize> h) noexcept {
  return crc32_update(kCrc32Init, std::span<const std::uint8_t>(h.data() + 4, 12));
}

// Validates a complete record held in memory: header valid, record.size() == header + length
// (no trailing bytes), CRC matches.
constexpr ParamRecordHeader check_param_record(std::span<const std::uint8_t> record,
                                               std::size_t max_payload) noexcept {
  ParamRecordHeader r;
  if (record.size() < kParamRecordHeaderSize) return r;
  const auto h = record.first<kParamRecordHeaderSize>();
  r = parse_param_record_header(h, max_payload);
  if (!r.valid) return r;
  if (record.size() != kParamRecordHeaderSize + r.length) {
    r.valid = false;
    return r;
  }
  const std::uint32_t crc =
      crc32_final(crc32_update(param_record_crc_start(h), record.subspan(kParamRecordHeaderSize)));
  r.valid = crc == r.crc;
  return r;
}

}  // namespace magvec::drivers
