// The Geometrics G-882 scalar magnetometer's line decoder. Input: 3 configuration bytes
// (preamble, analog channel count and Julian clock, signal threshold), then the byte stream.
// Invariants: every push() result is counted in the matching counter (samples; malformed or
// out_of_range for kMalformed; overflows) and nowhere else; crc_errors stays 0 (no checksum in
// the format); a reading is finite and within [min_field_nT, max_field_nT], its quality in [0, 1]
// (NaN without analog channels), flagged low-signal exactly when below the threshold, its
// sequence +1; encoding a decoded reading and decoding that line again gives the same reading
// and signal exactly; garbage_bytes never exceeds the bytes pushed.
#include <array>
#include <cmath>

#include "fuzz_check.hpp"
#include "magvec/drivers/g882.hpp"

using namespace magvec;
using namespace magvec::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::Bytes in(data, size);
  G882LineConfig cfg;
  static constexpr char kPreambles[] = {'$', '#', '*', 'A'};
  const std::uint8_t a = in.u8();
  cfg.preamble = kPreambles[a & 3u];
  cfg.julian_time = (a & 4u) != 0;
  cfg.analog_channels = static_cast<std::uint8_t>((a >> 3) % 10u);  // 9: clamped to 8
  if ((a & 0x80u) != 0) {
    cfg.min_field_nT = 0;
    cfg.max_field_nT = 199999.999;
  }
  cfg.min_signal = static_cast<std::uint16_t>(in.u8() * 40u);

  G882LineDecoder dec(cfg);
  std::uint64_t ok = 0, rejected = 0, overflow = 0, pushed = 0;
  std::uint32_t last_sequence = 0;
  hal::ScalarSample s;
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
        FUZZ_CHECK(std::isfinite(s.f_nT));
        FUZZ_CHECK(s.f_nT >= cfg.min_field_nT && s.f_nT <= cfg.max_field_nT);
        if (cfg.analog_channels == 0) {
          FUZZ_CHECK(std::isnan(s.quality) && s.flags == 0);
        } else {
          FUZZ_CHECK(s.quality >= 0 && s.quality <= 1);
          const auto signal = static_cast<std::uint16_t>(
              std::lround(s.quality * G882LineDecoder::kSignalFullScale));
          const bool low = cfg.min_signal != 0 && signal < cfg.min_signal;
          FUZZ_CHECK(((s.flags & hal::kScalarLowSignal) != 0) == low);
          // Round trip: the decoded reading has 3 decimals, so encoding it is exact.
          std::array<char, 96> line{};
          const std::size_t n = dec.encode(s.f_nT, signal, line);
          FUZZ_CHECK(n > 0);
          G882LineDecoder again(cfg);
          hal::ScalarSample r;
          int samples = 0;
          for (std::size_t i = 0; i < n; ++i)
            if (again.push(static_cast<std::uint8_t>(line[i]), 0, r) == hal::Status::kOk) ++samples;
          FUZZ_CHECK(samples == 1);
          FUZZ_CHECK(r.f_nT == s.f_nT && r.quality == s.quality && r.flags == s.flags);
        }
        break;
      }
      case hal::Status::kMalformed:
        ++rejected;
        break;
      case hal::Status::kOverflow:
        ++overflow;
        break;
      default:
        FUZZ_CHECK(false && "unexpected status");
    }
  }
  const hal::ScalarCounters& c = dec.counters();
  FUZZ_CHECK(c.samples == ok);
  FUZZ_CHECK(c.malformed + c.out_of_range == rejected);
  FUZZ_CHECK(c.overflows == overflow);
  FUZZ_CHECK(c.crc_errors == 0);
  FUZZ_CHECK(c.garbage_bytes <= pushed);
  return 0;
}
