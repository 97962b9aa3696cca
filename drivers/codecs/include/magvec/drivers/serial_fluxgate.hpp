// Serial fluxgate decoders: incremental (byte by byte), bounded memory, no heap, resynchronising
// after garbage, counting every rejection in hal::MagCounters.
//
// 1. AsciiLineDecoder: a configurable NMEA-like line format, e.g.
// "$MAG,12345.6,-2345.1,40000.0*hh\r\n"
//      [start_char] field {separator field} ['*' hh] ['\r'] '\n'
//    - start_char (default '$', 0 = none) opens a line; a start_char inside a line restarts it
//      (the partial line is counted as malformed), so a line that follows garbage is recovered.
//      Without a start_char, garbage is joined to the next line, which is then lost (documented
//      limitation of start-less formats).
//    - hh: NMEA 0183 checksum, XOR of every byte after start_char (or from the line start) up to
//      '*', two hex digits (either case). ChecksumMode decides whether it is
//      optional/required/absent.
//    - fields: `tag` (if non-empty) must equal field 0; x, y, z at configurable field indices;
//      decimal numbers (sign, digits, '.', exponent); value_nT = number * scale.
//    - at most kMaxLine bytes per line; longer lines are counted as overflow and skipped.
// 2. Hmr2300BinaryDecoder: Honeywell HMR2300 binary output ("*ddB" mode), 7 bytes per record:
//      XH XL YH YL ZH ZL 0Dh, each axis a signed 16-bit big-endian count, 15,000 counts per gauss
//      (the datasheet's table: +2.0 G = 30,000 = 7530h, -1.5 G = -22,500 = A8..h), so one count is
//      100000/15000 = 6.667 nT. Source: Honeywell HMR2300 datasheet, "Data formats".
//    The record has no checksum and the terminator 0Dh can also occur inside the data, so framing
//    is probabilistic: the decoder locks when two 0Dh terminators are exactly 7 bytes apart and
//    both records pass the range check (|count| <= max_abs_counts, default 30,000 = the +/-2 G full
//    scale), then emits both; while locked it checks the terminator of every record and drops lock
//    (counted as malformed) on a mismatch. Consequences, documented rather than hidden: after
//    garbage, a single isolated record (not followed by another within 7 bytes) is not recovered;
//    garbage that happens to contain two well-spaced 0Dh bytes with plausible data between can
//    yield a false record; the first record after (re)lock is delivered one record late.
//    Not verified: whether the instrument clips at +/-30,000 or can output larger codes.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/drivers/serial_framing.hpp"
#include "magvec/hal/clock.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/serial_port.hpp"

namespace magvec::drivers {

enum class ChecksumMode : std::uint8_t { kNone, kOptional, kRequired };

struct AsciiLineConfig {
  char start_char{'$'};  // 0 = lines start after the previous '\n'
  char separator{','};
  std::array<char, 12> tag{'M', 'A', 'G'};  // zero-terminated; empty = no tag check
  std::array<std::uint8_t, 3> field_of_axis{1, 2, 3};
  std::uint8_t field_count{4};  // exact number of fields; 0 = at least max index + 1
  double scale{1.0};            // nT per unit of the numbers in the line
  ChecksumMode checksum{ChecksumMode::kOptional};
};

class AsciiLineDecoder {
 public:
  static constexpr std::size_t kMaxLine = 96;  // bytes between start and '\n' (exclusive)
  static constexpr std::size_t kMaxFields = 12;

  explicit AsciiLineDecoder(const AsciiLineConfig& config) noexcept
      : config_(config), framer_(config.start_char) {}

  // Consumes one byte received at t_us. Returns kOk when it completed a valid line (out filled,
  // out.t_us = time of the line's first byte), kNoData when more bytes are needed, or the reason a
  // line was rejected (kCrcError, kMalformed, kOverflow).
  hal::Status push(std::uint8_t byte, std::uint64_t t_us, hal::MagnetometerSample& out) noexcept;

  // Feeds a block; calls on_sample(const hal::MagnetometerSample&) for each valid line.
  template <typename OnSample>
  void feed(std::span<const std::uint8_t> bytes, std::uint64_t t_us,
            OnSample&& on_sample) noexcept {
    hal::MagnetometerSample s;
    for (const std::uint8_t b : bytes) {
      if (push(b, t_us, s) == hal::Status::kOk)
        on_sample(static_cast<const hal::MagnetometerSample&>(s));
    }
  }

  const hal::MagCounters& counters() const noexcept { return counters_; }
  // Encoder for simulated devices and tests: writes one line with checksum (if `with_checksum`),
  // fields in the configured order (unused fields "0"). Returns the number of bytes, 0 if `out`
  // is too small.
  std::size_t encode(const std::array<double, 3>& m_nT, bool with_checksum,
                     std::span<char> out) const noexcept;

 private:
  hal::Status finish_line(hal::MagnetometerSample& out) noexcept;

  AsciiLineConfig config_;
  hal::MagCounters counters_{};
  LineFramer<kMaxLine> framer_;
  std::uint32_t sequence_{0};
};

struct Hmr2300Config {
  double nT_per_count{100000.0 / 15000.0};
  std::int32_t max_abs_counts{30000};
};

class Hmr2300BinaryDecoder {
 public:
  static constexpr std::size_t kRecordBytes = 7;
  static constexpr std::uint8_t kTerminator = 0x0D;

  explicit Hmr2300BinaryDecoder(const Hmr2300Config& config = {}) noexcept : config_(config) {}

  // Consumes one byte. Returns kOk with one record; on lock acquisition two records complete at
  // once: the older one is returned first and the newer one is delivered by the next call of
  // pending() (push() returns kOk and pending() returns true).
  hal::Status push(std::uint8_t byte, std::uint64_t t_us, hal::MagnetometerSample& out) noexcept;
  bool pending(hal::MagnetometerSample& out) noexcept;

  template <typename OnSample>
  void feed(std::span<const std::uint8_t> bytes, std::uint64_t t_us,
            OnSample&& on_sample) noexcept {
    hal::MagnetometerSample s;
    for (const std::uint8_t b : bytes) {
      if (push(b, t_us, s) == hal::Status::kOk) {
        on_sample(static_cast<const hal::MagnetometerSample&>(s));
        while (pending(s))
          on_sample(static_cast<const hal::MagnetometerSample&>(s));
      }
    }
  }

  bool locked() const noexcept { return locked_; }
  const hal::MagCounters& counters() const noexcept { return counters_; }
  static std::array<std::uint8_t, kRecordBytes> encode(
      const std::array<std::int16_t, 3>& counts) noexcept;

 private:
  static constexpr std::size_t kHistory = 2 * kRecordBytes;
  std::uint8_t at(std::uint64_t pos) const noexcept {
    return history_[static_cast<std::size_t>(pos % kHistory)];
  }
  bool plausible(std::uint64_t end_pos) const noexcept;  // record ending at end_pos (its 0Dh)
  void make_sample(std::uint64_t end_pos, std::uint64_t t_us,
                   hal::MagnetometerSample& out) noexcept;

  Hmr2300Config config_;
  hal::MagCounters counters_{};
  std::array<std::uint8_t, kHistory> history_{};
  std::uint64_t count_{0};         // bytes consumed so far; the current byte is at count_ - 1
  std::uint64_t expected_end_{0};  // while locked: position of the next terminator
  std::uint64_t last_emitted_end_{0};
  bool any_emitted_{false};
  bool locked_{false};
  bool has_pending_{false};
  hal::MagnetometerSample pending_{};
  std::uint32_t sequence_{0};
};

// hal::MagnetometerSource over a hal::SerialPort with one of the decoders above (SerialPump:
// chunked reads, the receive time minus `latency_us` becomes the sample time).
template <typename Decoder>
class SerialFluxgate final : public hal::MagnetometerSource {
 public:
  SerialFluxgate(hal::SerialPort& port, const hal::Clock& clock, Decoder decoder,
                 std::uint32_t latency_us = 0) noexcept
      : pump_(port, clock, decoder, latency_us) {}

  hal::Status read(hal::MagnetometerSample& out, std::uint32_t timeout_us) noexcept override {
    return pump_.read(out, timeout_us);
  }
  const hal::MagCounters& counters() const noexcept override {
    counters_ = pump_.decoder().counters();
    counters_.bus_errors += pump_.bus_errors();
    return counters_;
  }
  const Decoder& decoder() const noexcept { return pump_.decoder(); }

 private:
  SerialPump<Decoder, hal::MagnetometerSample> pump_;
  mutable hal::MagCounters counters_{};
};

}  // namespace magvec::drivers
