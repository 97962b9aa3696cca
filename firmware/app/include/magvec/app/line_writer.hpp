// Compact report lines without printf (newlib's printf/dtoa allocate, and the image links no
// heap): decimal integers, IEEE-754 bit patterns of doubles in hex (exact, parsed by the host
// test), and fixed-point decimals for the human-readable summary.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "magvec/app/board.hpp"

namespace magvec::app {

class LineWriter {
 public:
  static constexpr std::size_t kCapacity = 512;

  LineWriter& str(const char* s) noexcept {
    while (*s != '\0')
      put(*s++);
    return *this;
  }
  LineWriter& u(std::uint64_t v) noexcept {
    char tmp[24];
    std::size_t n = 0;
    do {
      tmp[n++] = static_cast<char>('0' + v % 10);
      v /= 10;
    } while (v != 0);
    while (n > 0)
      put(tmp[--n]);
    return *this;
  }
  LineWriter& i(std::int64_t v) noexcept {
    if (v < 0) {
      put('-');
      return u(static_cast<std::uint64_t>(-(v + 1)) + 1);
    }
    return u(static_cast<std::uint64_t>(v));
  }
  // The exact value: the 64-bit pattern of (double)v, 16 hex digits (float widens exactly).
  LineWriter& hex(double v) noexcept {
    std::uint64_t bits = 0;
    std::memcpy(&bits, &v, sizeof bits);
    static constexpr char kDigits[] = "0123456789abcdef";
    for (int k = 60; k >= 0; k -= 4)
      put(kDigits[(bits >> k) & 0xFu]);
    return *this;
  }
  // Fixed point with `decimals` digits (for humans; NaN/inf and huge values printed as words).
  LineWriter& fixed(double v, int decimals) noexcept {
    if (std::isnan(v)) return str("nan");
    if (!(std::fabs(v) < 1e15)) return str(v > 0 ? "inf" : "-inf");
    if (v < 0) {
      put('-');
      v = -v;
    }
    double scale = 1;
    for (int k = 0; k < decimals; ++k)
      scale *= 10;
    const auto total = static_cast<std::uint64_t>(std::llround(v * scale));
    const auto ipart = total / static_cast<std::uint64_t>(scale);
    std::uint64_t frac = total % static_cast<std::uint64_t>(scale);
    u(ipart);
    if (decimals > 0) {
      put('.');
      char tmp[20];
      for (int k = decimals - 1; k >= 0; --k) {
        tmp[k] = static_cast<char>('0' + frac % 10);
        frac /= 10;
      }
      for (int k = 0; k < decimals; ++k)
        put(tmp[k]);
    }
    return *this;
  }
  LineWriter& sp() noexcept {
    put(' ');
    return *this;
  }
  // Ends the line and sends it to the board's output.
  void end() noexcept {
    put('\n');
    flush();
  }

 private:
  void put(char c) noexcept {
    if (n_ == kCapacity) flush();
    buf_[n_++] = c;
  }
  void flush() noexcept {
    if (n_ > 0) board_write(buf_, n_);
    n_ = 0;
  }
  char buf_[kCapacity];
  std::size_t n_{0};
};

}  // namespace magvec::app
