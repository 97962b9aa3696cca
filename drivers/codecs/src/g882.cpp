// Geometrics G-882 line decoder and serial source; the format is documented in g882.hpp.
#include "magvec/drivers/g882.hpp"

#include <cmath>
#include <limits>
#include <string_view>

namespace magvec::drivers {
namespace {

bool is_digit(char c) noexcept {
  return c >= '0' && c <= '9';
}

// n digits at p (all checked by the caller's bounds): their value, or -1.
std::int32_t digits(const char* p, std::size_t n) noexcept {
  std::int32_t v = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (!is_digit(p[i])) return -1;
    v = v * 10 + (p[i] - '0');
  }
  return v;
}

// The Julian clock field: a non-empty, ordered subset of D ddd, H hh, M mm, S ss, _ cc.
bool julian_ok(const char* b, const char* e) noexcept {
  static constexpr std::array<char, 5> kTag{'D', 'H', 'M', 'S', '_'};
  static constexpr std::array<std::size_t, 5> kDigits{3, 2, 2, 2, 2};
  std::size_t next = 0;
  bool any = false;
  while (b != e) {
    std::size_t k = next;
    while (k < kTag.size() && kTag[k] != *b)
      ++k;
    if (k == kTag.size()) return false;
    ++b;
    if (static_cast<std::size_t>(e - b) < kDigits[k] || digits(b, kDigits[k]) < 0) return false;
    b += kDigits[k];
    next = k + 1;
    any = true;
  }
  return any;
}

}  // namespace

hal::Status G882LineDecoder::push(std::uint8_t byte, std::uint64_t t_us,
                                  hal::ScalarSample& out) noexcept {
  // A preamble inside a line restarts it: the partial line is lost, the new one recovered.
  return line_status(framer_.push(static_cast<char>(byte), t_us, counters_),
                     [&]() noexcept { return finish_line(out); });
}

hal::Status G882LineDecoder::finish_line(hal::ScalarSample& out) noexcept {
  const std::string_view line = framer_.line();
  const std::size_t n = line.size();
  const char* p = line.data();
  const char* const end = p + n;
  const auto malformed = [this] {
    ++counters_.malformed;
    return hal::Status::kMalformed;
  };
  // " 48123.456" or "148123.456"
  if (n < 10 || (p[0] != ' ' && p[0] != '1') || p[6] != '.') return malformed();
  const std::int32_t whole = digits(p + 1, 5);
  const std::int32_t milli = digits(p + 7, 3);
  if (whole < 0 || milli < 0) return malformed();
  p += 10;
  std::int32_t signal = -1;
  const std::uint8_t channels =
      config_.analog_channels > kMaxAnalogChannels ? kMaxAnalogChannels : config_.analog_channels;
  for (std::uint8_t ch = 0; ch < channels; ++ch) {
    if (end - p < 5 || p[0] != ',') return malformed();
    const std::int32_t v = digits(p + 1, 4);
    if (v < 0) return malformed();
    if (ch == 0) signal = v;
    p += 5;
  }
  if (p != end) {
    if (!config_.julian_time || *p != ',' || !julian_ok(p + 1, end)) return malformed();
  }
  const double f_nT = (line[0] == '1' ? 100000.0 : 0.0) + static_cast<double>(whole) +
                      static_cast<double>(milli) / 1000.0;
  if (!(f_nT >= config_.min_field_nT && f_nT <= config_.max_field_nT)) {
    ++counters_.out_of_range;
    return hal::Status::kMalformed;
  }
  out = hal::ScalarSample{};
  out.t_us = framer_.line_t_us();
  out.f_nT = f_nT;
  out.quality = signal >= 0 ? static_cast<double>(signal) / kSignalFullScale
                            : std::numeric_limits<double>::quiet_NaN();
  if (config_.min_signal != 0 && signal >= 0 && signal < config_.min_signal) {
    out.flags |= hal::kScalarLowSignal;
    ++counters_.low_signal;
  }
  out.sequence = sequence_++;
  ++counters_.samples;
  return hal::Status::kOk;
}

std::size_t G882LineDecoder::encode(double f_nT, std::uint16_t signal,
                                    std::span<char> out) const noexcept {
  if (!std::isfinite(f_nT) || f_nT < 0) return 0;
  const auto milli_total = static_cast<std::uint64_t>(std::llround(f_nT * 1000.0));
  if (milli_total >= 200'000'000) return 0;
  const std::uint8_t channels =
      config_.analog_channels > kMaxAnalogChannels ? kMaxAnalogChannels : config_.analog_channels;
  const std::size_t size = 1 + 10 + 5 * std::size_t{channels} + 2;
  if (out.size() < size) return 0;
  std::size_t i = 0;
  out[i++] = config_.preamble;
  out[i++] = milli_total >= 100'000'000 ? '1' : ' ';
  std::uint64_t whole = (milli_total / 1000) % 100000;
  std::uint64_t milli = milli_total % 1000;
  for (int k = 4; k >= 0; --k) {
    out[i + static_cast<std::size_t>(k)] = static_cast<char>('0' + whole % 10);
    whole /= 10;
  }
  i += 5;
  out[i++] = '.';
  for (int k = 2; k >= 0; --k) {
    out[i + static_cast<std::size_t>(k)] = static_cast<char>('0' + milli % 10);
    milli /= 10;
  }
  i += 3;
  for (std::uint8_t ch = 0; ch < channels; ++ch) {
    std::uint32_t v = ch == 0 ? (signal > 9999 ? 9999u : signal) : 0u;
    out[i++] = ',';
    for (int k = 3; k >= 0; --k) {
      out[i + static_cast<std::size_t>(k)] = static_cast<char>('0' + v % 10);
      v /= 10;
    }
    i += 4;
  }
  out[i++] = '\r';
  out[i++] = '\n';
  return i;
}

}  // namespace magvec::drivers
