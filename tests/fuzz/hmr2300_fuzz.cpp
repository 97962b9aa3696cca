// The Honeywell HMR2300 binary record decoder (7-byte records without a checksum). Input: 1
// configuration byte (range limit), then the byte stream.
// Invariants: each delivered record is the 7 stream bytes ending at a 0Dh terminator, decoded to
// the counts it reports, within the range limit; delivered records never share a byte (no record
// delivered twice, no false record made of an already delivered one) and come in stream order;
// counters.samples equals the records delivered; the sequence increments by one.
#include <cmath>
#include <vector>

#include "fuzz_check.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"

using namespace magvec;
using namespace magvec::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::Bytes in(data, size);
  Hmr2300Config cfg;
  const std::uint8_t c0 = in.u8();
  if ((c0 & 1u) != 0) cfg.max_abs_counts = 32767;
  const std::vector<std::uint8_t> stream(in.data(), in.data() + in.size());

  Hmr2300BinaryDecoder dec(cfg);
  std::uint64_t delivered = 0;
  std::uint32_t last_sequence = 0;
  bool have_last_end = false;
  std::size_t last_end = 0;
  auto check_record = [&](const hal::MagnetometerSample& s, std::size_t end) {
    FUZZ_CHECK(end >= 6 && end < stream.size());
    FUZZ_CHECK(stream[end] == Hmr2300BinaryDecoder::kTerminator);
    if (have_last_end) FUZZ_CHECK(end - 6 > last_end);  // after, and disjoint from, the last one
    have_last_end = true;
    last_end = end;
    for (std::size_t axis = 0; axis < 3; ++axis) {
      const std::size_t p = end - 6 + 2 * axis;
      const auto v =
          static_cast<std::int16_t>(static_cast<std::uint16_t>((stream[p] << 8) | stream[p + 1]));
      FUZZ_CHECK(s.raw[axis] == v);
      FUZZ_CHECK(std::abs(s.raw[axis]) <= cfg.max_abs_counts);
      FUZZ_CHECK(s.m_nT[axis] == static_cast<double>(v) * cfg.nT_per_count);
    }
    if (delivered > 0) FUZZ_CHECK(s.sequence == last_sequence + 1);
    last_sequence = s.sequence;
    ++delivered;
  };
  hal::MagnetometerSample s;
  for (std::size_t pos = 0; pos < stream.size(); ++pos) {
    const hal::Status st = dec.push(stream[pos], pos, s);
    if (st == hal::Status::kNoData) continue;
    FUZZ_CHECK(st == hal::Status::kOk);
    hal::MagnetometerSample newer;
    if (dec.pending(newer)) {
      // Lock acquisition: the older record ends 7 bytes before this terminator.
      FUZZ_CHECK(pos >= 7);
      check_record(s, pos - 7);
      check_record(newer, pos);
    } else {
      check_record(s, pos);
    }
    FUZZ_CHECK(!dec.pending(newer));
  }
  FUZZ_CHECK(dec.counters().samples == delivered);
  FUZZ_CHECK(dec.counters().garbage_bytes <= stream.size());
  return 0;
}
