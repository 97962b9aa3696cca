// Byte-level pieces shared by the serial instruments' drivers (the ASCII fluxgate line format and
// the HMR2300 in serial_fluxgate.hpp, the G-882 scalar magnetometer in g882.hpp):
//   LineFramer   assembles '\n'-terminated lines, opened by a start character (or, without one,
//                by the first byte after the previous line), resynchronising after garbage and
//                bounding the line length;
//   SerialPump   pulls bytes from a hal::SerialPort in chunks, time-stamps each chunk with its
//                receive time minus the configured latency and feeds them to a byte decoder.
// Each format keeps its own field parsing and counters; what differs between the instruments is
// only the line's content, not how bytes become lines. Bounded memory, no heap, noexcept.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>

#include "magvec/hal/clock.hpp"
#include "magvec/hal/serial_port.hpp"
#include "magvec/hal/status.hpp"

namespace magvec::drivers {

// What one byte did to the line being assembled.
enum class LineEvent : std::uint8_t {
  kNone,       // more bytes needed (or a byte skipped while resynchronising)
  kLine,       // a line ended: line() holds it (without '\r' '\n'), line_t_us() its first byte
  kRestarted,  // a start character inside a line: the partial line is lost, a new one begun
  kOverflow,   // the line exceeded kMaxLine bytes: skipped up to the next '\n'
};

// A line decoder's push() result for what its byte did: a finished line is parsed by `finish`
// (the format's own field parsing), a restarted line is malformed, an overlong one an overflow.
template <typename Finish>
hal::Status line_status(LineEvent event, Finish&& finish) noexcept {
  switch (event) {
    case LineEvent::kNone:
      return hal::Status::kNoData;
    case LineEvent::kLine:
      return finish();
    case LineEvent::kRestarted:
      return hal::Status::kMalformed;
    case LineEvent::kOverflow:
      return hal::Status::kOverflow;
  }
  return hal::Status::kNoData;
}

// Counters: any struct with malformed, overflows and garbage_bytes (hal::MagCounters,
// hal::ScalarCounters). A restarted line counts as malformed, its bytes and the skipped ones as
// garbage.
template <std::size_t kMaxLine>
class LineFramer {
 public:
  // start_char: the byte that opens a line, '\0' for formats without one (a line then starts
  // with any byte after the previous '\n'; garbage before it is joined to the line and the line
  // is lost to the format's check — the documented limitation of start-less formats).
  explicit LineFramer(char start_char) noexcept : start_char_(start_char) {}

  template <typename Counters>
  LineEvent push(char c, std::uint64_t t_us, Counters& counters) noexcept {
    const bool has_start = start_char_ != '\0';
    if (has_start && c == start_char_) {
      LineEvent event = LineEvent::kNone;
      if (state_ == State::kInLine) {
        ++counters.malformed;
        counters.garbage_bytes += static_cast<std::uint32_t>(len_ + 1);
        event = LineEvent::kRestarted;
      }
      start(t_us);
      return event;
    }
    switch (state_) {
      case State::kIdle:
        if (has_start) {
          ++counters.garbage_bytes;
          return LineEvent::kNone;
        }
        if (c == '\n' || c == '\r') return LineEvent::kNone;  // an empty line
        start(t_us);
        break;
      case State::kDiscard:
        ++counters.garbage_bytes;
        if (c == '\n') state_ = State::kIdle;
        return LineEvent::kNone;
      case State::kInLine:
        break;
    }
    if (c == '\n') {
      state_ = State::kIdle;
      return LineEvent::kLine;
    }
    if (len_ == kMaxLine) {
      ++counters.overflows;
      counters.garbage_bytes += static_cast<std::uint32_t>(len_ + 1);
      state_ = State::kDiscard;
      return LineEvent::kOverflow;
    }
    line_[len_++] = c;
    return LineEvent::kNone;
  }

  // The last completed line, without its start character and its "\r\n" (a lone '\n' too).
  std::string_view line() const noexcept {
    std::size_t n = len_;
    if (n > 0 && line_[n - 1] == '\r') --n;
    return {line_.data(), n};
  }
  std::uint64_t line_t_us() const noexcept { return line_t_us_; }

 private:
  enum class State : std::uint8_t { kIdle, kInLine, kDiscard };
  void start(std::uint64_t t_us) noexcept {
    state_ = State::kInLine;
    len_ = 0;
    line_t_us_ = t_us;
  }

  char start_char_;
  State state_{State::kIdle};
  std::array<char, kMaxLine> line_{};
  std::size_t len_{0};
  std::uint64_t line_t_us_{0};
};

// Reads a byte-oriented instrument through a hal::SerialPort. Decoder:
//   hal::Status push(std::uint8_t byte, std::uint64_t t_us, Sample& out) noexcept
//     kOk with a sample, kNoData for more bytes, another status for a rejected record;
//   optionally bool pending(Sample& out) noexcept (a decoder that completes two records at once).
// A rejected record is returned as its status (as an ADC source reports a bad frame); the bytes
// after it stay for the next call. Bounded work per call: at most kMaxChunks port reads, the first
// may wait up to timeout_us, the rest poll.
template <typename Decoder, typename Sample>
class SerialPump {
 public:
  static constexpr std::size_t kChunk = 64;
  static constexpr int kMaxChunks = 16;

  SerialPump(hal::SerialPort& port, const hal::Clock& clock, Decoder decoder,
             std::uint32_t latency_us) noexcept
      : port_(port), clock_(clock), decoder_(decoder), latency_us_(latency_us) {}

  hal::Status read(Sample& out, std::uint32_t timeout_us) noexcept {
    for (int attempt = 0; attempt < kMaxChunks; ++attempt) {
      const hal::Status t = take_from_buffer(out);
      if (t != hal::Status::kNoData) return t;
      std::size_t n = 0;
      const hal::Status s = port_.read(buf_, n, attempt == 0 ? timeout_us : 0);
      if (s != hal::Status::kOk && s != hal::Status::kTimeout && s != hal::Status::kNoData) {
        ++bus_errors_;
        return s;
      }
      if (n == 0) return attempt == 0 ? hal::Status::kTimeout : hal::Status::kNoData;
      const std::uint64_t now = clock_.now_us();
      rx_t_us_ = now > latency_us_ ? now - latency_us_ : 0;
      pos_ = 0;
      len_ = n;
    }
    return take_from_buffer(out);
  }

  const Decoder& decoder() const noexcept { return decoder_; }
  std::uint32_t bus_errors() const noexcept { return bus_errors_; }

 private:
  // kOk (a sample), kNoData (the buffer is used up) or the decoder's rejection of a record.
  hal::Status take_from_buffer(Sample& out) noexcept {
    if constexpr (requires(Decoder d, Sample s) { d.pending(s); }) {
      if (decoder_.pending(out)) return hal::Status::kOk;
    }
    while (pos_ < len_) {
      const hal::Status s = decoder_.push(buf_[pos_++], rx_t_us_, out);
      if (s != hal::Status::kNoData) return s;
    }
    return hal::Status::kNoData;
  }

  hal::SerialPort& port_;
  const hal::Clock& clock_;
  Decoder decoder_;
  std::uint32_t latency_us_;
  std::array<std::uint8_t, kChunk> buf_{};
  std::size_t pos_{0};
  std::size_t len_{0};
  std::uint64_t rx_t_us_{0};
  std::uint32_t bus_errors_{0};
};

}  // namespace magvec::drivers
