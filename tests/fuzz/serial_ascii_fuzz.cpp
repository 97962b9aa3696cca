// The ASCII fluxgate line decoder (serial magnetometers). Input: 6 configuration bytes (start
// character, separator, checksum mode, field count and axis fields, scale), then the byte stream.
// Invariants: every push() result is counted in the matching counter (samples, crc_errors,
// malformed, overflows) and nowhere else; a sample's field is finite and its sequence increments
// by one; encoding a decoded sample and decoding that line again gives the same field (to the
// encoder's 3 decimals); garbage_bytes never exceeds the bytes pushed.
#include <array>
#include <cmath>

#include "fuzz_check.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"

using namespace magvec;
using namespace magvec::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::Bytes in(data, size);
  AsciiLineConfig cfg;
  const std::uint8_t a = in.u8();
  cfg.start_char = (a & 1u) != 0 ? '$' : '\0';
  static constexpr char kSeparators[] = {',', ';', ' ', '\t'};
  cfg.separator = kSeparators[(a >> 1) & 3u];
  cfg.checksum = static_cast<ChecksumMode>(((a >> 3) & 3u) % 3u);
  if ((a & 0x20u) != 0) cfg.tag = {};
  const std::uint8_t b = in.u8();
  cfg.field_count = static_cast<std::uint8_t>(b % 8u);  // 0: at least the axis fields
  for (std::size_t k = 0; k < 3; ++k)
    cfg.field_of_axis[k] = static_cast<std::uint8_t>(1 + (in.u8() % 6u));
  static constexpr double kScales[] = {1.0, 1000.0, 0.1, 100000.0};
  cfg.scale = kScales[in.u8() & 3u];

  AsciiLineDecoder dec(cfg);
  std::uint64_t ok = 0, crc = 0, malformed = 0, overflow = 0, pushed = 0;
  std::uint32_t last_sequence = 0;
  hal::MagnetometerSample s;
  while (in.size() > 0) {
    const std::uint8_t byte = in.u8();
    ++pushed;
    const hal::Status st = dec.push(byte, pushed, s);
    switch (st) {
      case hal::Status::kNoData:
        break;
      case hal::Status::kOk: {
        ++ok;
        if (ok > 1) FUZZ_CHECK(s.sequence == last_sequence + 1);
        last_sequence = s.sequence;
        FUZZ_CHECK(s.t_us >= 1 && s.t_us <= pushed);
        for (const double v : s.m_nT)
          FUZZ_CHECK(std::isfinite(v));
        // Round trip through the encoder (values it can write: |units| < 1e15).
        std::array<char, 256> line{};
        const std::array<double, 3> m{s.m_nT[0], s.m_nT[1], s.m_nT[2]};
        const std::size_t n = dec.encode(m, cfg.checksum != ChecksumMode::kNone, line);
        bool encodable = true;
        for (const double v : m)
          encodable = encodable && std::abs(v / cfg.scale) < 1e14;
        if (encodable && n > 0 && n <= AsciiLineDecoder::kMaxLine) {
          AsciiLineDecoder again(cfg);
          int samples = 0;
          hal::MagnetometerSample r;
          for (std::size_t i = 0; i < n; ++i) {
            if (again.push(static_cast<std::uint8_t>(line[i]), 0, r) == hal::Status::kOk) ++samples;
          }
          FUZZ_CHECK(samples == 1);
          for (std::size_t k = 0; k < 3; ++k) {
            const double tol = (0.0005 + 1e-12 * std::abs(m[k] / cfg.scale)) * cfg.scale;
            FUZZ_CHECK(std::abs(r.m_nT[k] - m[k]) <= tol * (1 + 1e-9));
          }
        }
        break;
      }
      case hal::Status::kCrcError:
        ++crc;
        break;
      case hal::Status::kMalformed:
        ++malformed;
        break;
      case hal::Status::kOverflow:
        ++overflow;
        break;
      default:
        FUZZ_CHECK(false && "unexpected status");
    }
  }
  const hal::MagCounters& c = dec.counters();
  FUZZ_CHECK(c.samples == ok);
  FUZZ_CHECK(c.crc_errors == crc);
  FUZZ_CHECK(c.malformed == malformed);
  FUZZ_CHECK(c.overflows == overflow);
  FUZZ_CHECK(c.garbage_bytes <= pushed);
  return 0;
}
