// Geometrics G-882 cesium marine magnetometer: decoder of its serial ASCII output, the encoder the
// simulated instrument uses, and a hal::ScalarSource over a hal::SerialPort.
//
// Source: "G-882 Cesium Marine Magnetometer Operation Manual" (Geometrics Inc.), section 4.4 on
// the CM-201 counter module: page 37 (default output: 9600 baud 8N1, 10 Hz, ASCII; the line
// layout below), page 47 (example "$ 54369.127,1234,5678,0000": three analog fields),
// pages 51-52 (Julian clock fields, preamble command "Px"). Read from the manual's pages as
// published online (easymanua.ls); the manual's revision is not printed on those pages and is not
// verified here.
//
// Line (every character printable; one reading per line):
//   char 1      preamble, '$' by default (settable with the counter's 'P' command)
//   char 2      '1' or a blank: the hundred-thousands digit of the reading
//   chars 3-11  five digits, '.', three digits: the reading in nT (e.g. " 48123.456")
//   then        ",dddd" per enabled A/D channel: channel 0 (always first) is the Larmor signal
//               level, 0..9999 for 0..5 V; channels 1, 2 (depth, altitude) and 3-7 when enabled
//   then        optionally ",DdddHhhMmmSss_cc" (Julian clock: any subset of day, hour, minute,
//               second, 10-ms fields, in that order) when julian_time is configured
//   end         CR LF (a lone LF is accepted)
// The format has no checksum: integrity rests on the fixed layout, which the decoder checks
// character by character (crc_errors stays 0 for this format). The Julian clock is not used: the
// host time stamps the line (receive time minus latency_us; assumed, not documented: the reading
// is an average over the cycle before the line, so the latency should be about half a cycle plus
// the line's transmission time, 18.75 ms for the 18 characters of a one-channel line at 9600
// baud 8N1).
// Range: the G-882 specification gives an operating range of 17,000 to 100,000 nT; a well-formed
// reading outside [min_field_nT, max_field_nT] is counted as out of range and rejected. What the
// counter prints while the sensor is in a dead zone is not documented on those pages; a low
// signal level (min_signal) is the documented quality indication.
// Bounded memory, no heap, noexcept: also usable in the MCU image.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/drivers/serial_framing.hpp"
#include "magvec/hal/clock.hpp"
#include "magvec/hal/scalar_source.hpp"
#include "magvec/hal/serial_port.hpp"

namespace magvec::drivers {

struct G882LineConfig {
  char preamble{'$'};
  std::uint8_t analog_channels{1};  // 0..8 ",dddd" fields; channel 0 (the first) = signal level
  bool julian_time{false};          // accept the trailing Julian clock field
  double min_field_nT{17000};
  double max_field_nT{100000};
  // Channel-0 counts below which a reading is flagged kScalarLowSignal (0 = never). The manual
  // gives no threshold: set it from the instrument's signal level in a known-good run.
  std::uint16_t min_signal{0};
};

class G882LineDecoder {
 public:
  static constexpr std::size_t kMaxLine = 64;  // bytes after the preamble up to '\n' (exclusive)
  static constexpr std::uint8_t kMaxAnalogChannels = 8;
  static constexpr double kSignalFullScale = 9999.0;

  explicit G882LineDecoder(const G882LineConfig& config) noexcept
      : config_(config), framer_(config.preamble) {}

  // Consumes one byte received at t_us. kOk when it completed a valid line (out filled, out.t_us
  // = time of the line's preamble byte); kNoData when more bytes are needed; kMalformed (also for
  // an out-of-range reading, counted separately) or kOverflow for a rejected line.
  hal::Status push(std::uint8_t byte, std::uint64_t t_us, hal::ScalarSample& out) noexcept;

  const hal::ScalarCounters& counters() const noexcept { return counters_; }
  const G882LineConfig& config() const noexcept { return config_; }

  // Writes one line (reading rounded to 0.001 nT, channel 0 = signal, the other channels 0000,
  // CR LF). Returns the byte count, 0 when the reading cannot be written in the format (negative,
  // >= 200,000 nT, not finite) or `out` is too small.
  std::size_t encode(double f_nT, std::uint16_t signal, std::span<char> out) const noexcept;

 private:
  hal::Status finish_line(hal::ScalarSample& out) noexcept;

  G882LineConfig config_;
  hal::ScalarCounters counters_{};
  LineFramer<kMaxLine> framer_;
  std::uint32_t sequence_{0};
};

// hal::ScalarSource over a hal::SerialPort (a termios tty on Linux, a simulated instrument in
// tests) through SerialPump: chunked reads, the receive time minus latency_us becomes the time
// stamp, a rejected line is returned as its status and the bytes after it stay for the next call.
class SerialScalarSource final : public hal::ScalarSource {
 public:
  SerialScalarSource(hal::SerialPort& port, const hal::Clock& clock, G882LineDecoder decoder,
                     std::uint32_t latency_us = 0) noexcept
      : pump_(port, clock, decoder, latency_us) {}

  hal::Status read(hal::ScalarSample& out, std::uint32_t timeout_us) noexcept override {
    return pump_.read(out, timeout_us);
  }
  const hal::ScalarCounters& counters() const noexcept override {
    counters_ = pump_.decoder().counters();
    counters_.bus_errors += pump_.bus_errors();
    return counters_;
  }
  const G882LineDecoder& decoder() const noexcept { return pump_.decoder(); }

 private:
  SerialPump<G882LineDecoder, hal::ScalarSample> pump_;
  mutable hal::ScalarCounters counters_{};
};

}  // namespace magvec::drivers
