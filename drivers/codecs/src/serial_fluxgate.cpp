// Serial fluxgate decoders; formats documented in serial_fluxgate.hpp.
#include "magvec/drivers/serial_fluxgate.hpp"

#include <cmath>
#include <string_view>

#include "magvec/drivers/crc.hpp"

namespace magvec::drivers {
namespace {

int hex_value(char c) noexcept {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

// Decimal number [+-]digits[.digits][(e|E)[+-]digits], the whole range [b, e) must be consumed.
// Up to 18 significant digits are kept exactly; the scaling by a power of ten is done once.
bool parse_decimal(const char* b, const char* e, double& out) noexcept {
  if (b == e) return false;
  bool negative = false;
  if (*b == '+' || *b == '-') {
    negative = *b == '-';
    ++b;
  }
  std::uint64_t mantissa = 0;
  int digits = 0;
  int exponent = 0;
  bool any_digit = false;
  for (; b != e && *b >= '0' && *b <= '9'; ++b) {
    any_digit = true;
    if (digits < 18) {
      mantissa = mantissa * 10 + static_cast<std::uint64_t>(*b - '0');
      if (mantissa != 0) ++digits;
    } else {
      ++exponent;
    }
  }
  if (b != e && *b == '.') {
    ++b;
    for (; b != e && *b >= '0' && *b <= '9'; ++b) {
      any_digit = true;
      if (digits < 18) {
        mantissa = mantissa * 10 + static_cast<std::uint64_t>(*b - '0');
        if (mantissa != 0) ++digits;
        --exponent;
      }
    }
  }
  if (!any_digit) return false;
  if (b != e && (*b == 'e' || *b == 'E')) {
    ++b;
    bool exp_negative = false;
    if (b != e && (*b == '+' || *b == '-')) {
      exp_negative = *b == '-';
      ++b;
    }
    if (b == e) return false;
    int ex = 0;
    for (; b != e && *b >= '0' && *b <= '9'; ++b) {
      if (ex < 1000) ex = ex * 10 + (*b - '0');
    }
    exponent += exp_negative ? -ex : ex;
  }
  if (b != e) return false;
  if (exponent < -300 || exponent > 300) return false;
  double value = static_cast<double>(mantissa);
  double p = 1.0;
  for (int i = 0; i < (exponent < 0 ? -exponent : exponent); ++i)
    p *= 10.0;
  value = exponent < 0 ? value / p : value * p;
  if (!std::isfinite(value)) return false;
  out = negative ? -value : value;
  return true;
}

// Writes v with 3 decimals; returns bytes written or 0 if it does not fit.
std::size_t format_fixed3(double v, std::span<char> out) noexcept {
  if (!std::isfinite(v) || std::fabs(v) >= 1e15) return 0;
  char tmp[32];
  std::size_t n = 0;
  const bool negative = v < 0;
  const auto milli = static_cast<std::uint64_t>(std::llround(std::fabs(v) * 1000.0));
  std::uint64_t int_part = milli / 1000;
  const std::uint64_t frac = milli % 1000;
  tmp[n++] = static_cast<char>('0' + frac % 10);
  tmp[n++] = static_cast<char>('0' + (frac / 10) % 10);
  tmp[n++] = static_cast<char>('0' + frac / 100);
  tmp[n++] = '.';
  do {
    tmp[n++] = static_cast<char>('0' + int_part % 10);
    int_part /= 10;
  } while (int_part != 0);
  if (negative && milli != 0) tmp[n++] = '-';
  if (n > out.size()) return 0;
  for (std::size_t i = 0; i < n; ++i)
    out[i] = tmp[n - 1 - i];
  return n;
}

}  // namespace

hal::Status AsciiLineDecoder::push(std::uint8_t byte, std::uint64_t t_us,
                                   hal::MagnetometerSample& out) noexcept {
  return line_status(framer_.push(static_cast<char>(byte), t_us, counters_),
                     [&]() noexcept { return finish_line(out); });
}

hal::Status AsciiLineDecoder::finish_line(hal::MagnetometerSample& out) noexcept {
  const std::string_view line = framer_.line();
  const std::size_t n = line.size();
  // Checksum: "*hh" at the end.
  const char* begin = line.data();
  const char* end = line.data() + n;
  bool has_checksum = false;
  if (n >= 3 && line[n - 3] == '*') {
    const int hi = hex_value(line[n - 2]);
    const int lo = hex_value(line[n - 1]);
    if (hi < 0 || lo < 0) {
      ++counters_.malformed;
      return hal::Status::kMalformed;
    }
    has_checksum = true;
    end = line.data() + n - 3;
    const std::uint8_t expected = static_cast<std::uint8_t>(hi * 16 + lo);
    std::uint8_t x = 0;
    for (const char* p = begin; p != end; ++p)
      x = static_cast<std::uint8_t>(x ^ static_cast<std::uint8_t>(*p));
    if (config_.checksum == ChecksumMode::kNone) {
      ++counters_.malformed;
      return hal::Status::kMalformed;
    }
    if (x != expected) {
      ++counters_.crc_errors;
      return hal::Status::kCrcError;
    }
  }
  if (!has_checksum && config_.checksum == ChecksumMode::kRequired) {
    ++counters_.malformed;
    return hal::Status::kMalformed;
  }
  // Split into fields.
  std::array<const char*, kMaxFields + 1> starts{};
  std::size_t fields = 0;
  starts[fields++] = begin;
  for (const char* p = begin; p != end; ++p) {
    if (*p == config_.separator) {
      if (fields == kMaxFields) {
        ++counters_.malformed;
        return hal::Status::kMalformed;
      }
      starts[fields++] = p + 1;
    }
  }
  starts[fields] = end + 1;  // sentinel: field i spans [starts[i], starts[i+1] - 1)
  std::size_t needed = 0;
  for (const std::uint8_t f : config_.field_of_axis)
    needed = f + 1u > needed ? f + 1u : needed;
  if ((config_.field_count != 0 && fields != config_.field_count) || fields < needed) {
    ++counters_.malformed;
    return hal::Status::kMalformed;
  }
  if (config_.tag[0] != '\0') {
    const char* f = starts[0];
    const char* f_end = starts[1] - 1;
    std::size_t i = 0;
    for (; i < config_.tag.size() && config_.tag[i] != '\0'; ++i) {
      if (f + i == f_end || f[i] != config_.tag[i]) break;
    }
    const bool tag_done = i == config_.tag.size() || config_.tag[i] == '\0';
    if (!tag_done || f + i != f_end) {
      ++counters_.malformed;
      return hal::Status::kMalformed;
    }
  }
  std::array<double, 3> v{};
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const std::uint8_t f = config_.field_of_axis[axis];
    if (!parse_decimal(starts[f], starts[f + 1u] - 1, v[axis])) {
      ++counters_.malformed;
      return hal::Status::kMalformed;
    }
  }
  for (std::size_t axis = 0; axis < 3; ++axis) {
    out.m_nT[axis] = v[axis] * config_.scale;
    out.raw[axis] = 0;
  }
  out.t_us = framer_.line_t_us();
  out.flags = 0;
  out.sequence = sequence_++;
  ++counters_.samples;
  return hal::Status::kOk;
}

std::size_t AsciiLineDecoder::encode(const std::array<double, 3>& m_nT, bool with_checksum,
                                     std::span<char> out) const noexcept {
  std::size_t n = 0;
  auto put = [&](char c) {
    if (n < out.size()) out[n] = c;
    ++n;
  };
  if (config_.start_char != '\0') put(config_.start_char);
  const std::size_t body_start = n;
  std::size_t needed = 0;
  for (const std::uint8_t f : config_.field_of_axis)
    needed = f + 1u > needed ? f + 1u : needed;
  const std::size_t fields = config_.field_count != 0 ? config_.field_count : needed;
  for (std::size_t f = 0; f < fields; ++f) {
    if (f > 0) put(config_.separator);
    int axis = -1;
    for (int a = 0; a < 3; ++a) {
      if (config_.field_of_axis[static_cast<std::size_t>(a)] == f) axis = a;
    }
    if (axis >= 0) {
      const double units = m_nT[static_cast<std::size_t>(axis)] / config_.scale;
      const std::size_t w = n < out.size() ? format_fixed3(units, out.subspan(n)) : 0;
      if (w == 0) return 0;
      n += w;
    } else if (f == 0 && config_.tag[0] != '\0') {
      for (std::size_t i = 0; i < config_.tag.size() && config_.tag[i] != '\0'; ++i)
        put(config_.tag[i]);
    } else {
      put('0');
    }
  }
  if (with_checksum) {
    if (n > out.size()) return 0;
    const std::uint8_t x = xor_checksum(std::span<const std::uint8_t>(
        reinterpret_cast<const std::uint8_t*>(out.data()) + body_start, n - body_start));
    static constexpr char kHex[] = "0123456789ABCDEF";
    put('*');
    put(kHex[x >> 4]);
    put(kHex[x & 15]);
  }
  put('\r');
  put('\n');
  return n <= out.size() ? n : 0;
}

// ---------------------------------------------------------------- HMR2300 binary

std::array<std::uint8_t, Hmr2300BinaryDecoder::kRecordBytes> Hmr2300BinaryDecoder::encode(
    const std::array<std::int16_t, 3>& counts) noexcept {
  std::array<std::uint8_t, kRecordBytes> r{};
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const auto u = static_cast<std::uint16_t>(counts[axis]);
    r[2 * axis] = static_cast<std::uint8_t>(u >> 8);
    r[2 * axis + 1] = static_cast<std::uint8_t>(u);
  }
  r[6] = kTerminator;
  return r;
}

bool Hmr2300BinaryDecoder::plausible(std::uint64_t end_pos) const noexcept {
  if (at(end_pos) != kTerminator) return false;
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const std::uint64_t p = end_pos - 6 + 2 * axis;
    const auto v = static_cast<std::int16_t>(static_cast<std::uint16_t>((at(p) << 8) | at(p + 1)));
    if (v > config_.max_abs_counts || v < -config_.max_abs_counts) return false;
  }
  return true;
}

void Hmr2300BinaryDecoder::make_sample(std::uint64_t end_pos, std::uint64_t t_us,
                                       hal::MagnetometerSample& out) noexcept {
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const std::uint64_t p = end_pos - 6 + 2 * axis;
    const auto v = static_cast<std::int16_t>(static_cast<std::uint16_t>((at(p) << 8) | at(p + 1)));
    out.raw[axis] = v;
    out.m_nT[axis] = static_cast<double>(v) * config_.nT_per_count;
  }
  out.t_us = t_us;
  out.flags = 0;
  out.sequence = sequence_++;
  ++counters_.samples;
  // Everything between the previous record and this one was skipped.
  const std::uint64_t start = end_pos - 6;
  const std::uint64_t prev_next = any_emitted_ ? last_emitted_end_ + 1 : 0;
  if (start > prev_next) counters_.garbage_bytes += static_cast<std::uint32_t>(start - prev_next);
  last_emitted_end_ = end_pos;
  any_emitted_ = true;
}

bool Hmr2300BinaryDecoder::pending(hal::MagnetometerSample& out) noexcept {
  if (!has_pending_) return false;
  out = pending_;
  has_pending_ = false;
  return true;
}

hal::Status Hmr2300BinaryDecoder::push(std::uint8_t byte, std::uint64_t t_us,
                                       hal::MagnetometerSample& out) noexcept {
  const std::uint64_t pos = count_++;
  history_[static_cast<std::size_t>(pos % kHistory)] = byte;
  if (locked_) {
    if (pos != expected_end_) return hal::Status::kNoData;
    if (plausible(pos)) {
      expected_end_ = pos + kRecordBytes;
      make_sample(pos, t_us, out);
      return hal::Status::kOk;
    }
    locked_ = false;  // terminator missing or data out of range: resynchronise
    ++counters_.malformed;
  }
  if (byte != kTerminator || pos < kHistory - 1) return hal::Status::kNoData;
  const std::uint64_t prev_end = pos - kRecordBytes;
  // A candidate record [end - 6, end] is new only if it starts after the last delivered byte: a
  // candidate sharing even one byte with a delivered record would repeat data as a false sample.
  const auto fresh = [this](std::uint64_t end) {
    return !any_emitted_ || end - (kRecordBytes - 1) > last_emitted_end_;
  };
  if (!fresh(pos)) return hal::Status::kNoData;
  if (any_emitted_ && prev_end == last_emitted_end_) {
    // The older candidate is the last delivered record itself: the newer one continues it.
    if (!plausible(pos)) return hal::Status::kNoData;
    locked_ = true;
    expected_end_ = pos + kRecordBytes;
    make_sample(pos, t_us, out);
    return hal::Status::kOk;
  }
  // Otherwise both candidates must be new (a partial overlap is no evidence of framing).
  if (!fresh(prev_end)) return hal::Status::kNoData;
  if (!plausible(prev_end) || !plausible(pos)) return hal::Status::kNoData;
  locked_ = true;
  expected_end_ = pos + kRecordBytes;
  make_sample(prev_end, t_us, out);
  make_sample(pos, t_us, pending_);
  has_pending_ = true;
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
