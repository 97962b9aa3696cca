// The firmware image's hal::RecordSink: one text line per output record on a byte stream
// (hal::SerialPort: the board's UART on hardware, the semihosting console under qemu, stdout in
// the host twin). No printf (newlib's allocates): values are IEEE-754 double bit patterns in hex,
// exact and cheap to format, decoded by tests/mcu/compare_app_runs.py:
//   MV rec <t_us> <flags hex> <cal_id> <raw x y z> <h_s x y z> <F> <sigma_F> <h_n E N U>
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <span>

#include "magvec/hal/record_sink.hpp"
#include "magvec/hal/serial_port.hpp"

namespace magvec::app {

class RecordLineSink final : public hal::RecordSink {
 public:
  explicit RecordLineSink(hal::SerialPort& port) noexcept : port_(port) {}

  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    n_ = 0;
    put("MV rec ");
    dec(r.t_us);
    put(' ');
    hex32(r.flags);
    put(' ');
    dec(r.cal_id);
    for (const double v : r.raw_nT)
      hex64(v);
    for (const double v : r.h_s_nT)
      hex64(v);
    hex64(r.f_nT);
    hex64(r.sigma_f_nT);
    for (const double v : r.h_n_nT)
      hex64(v);
    put('\n');
    std::size_t written = 0;
    const hal::Status s = port_.write(std::span<const std::uint8_t>(line_, n_), written);
    if (s == hal::Status::kOk && written == n_) {
      ++emitted_;
      return hal::Status::kOk;
    }
    ++failed_;
    return s == hal::Status::kOk ? hal::Status::kBusError : s;
  }
  std::uint32_t emitted() const noexcept { return emitted_; }
  std::uint32_t failed() const noexcept { return failed_; }

 private:
  // 7 + 20 + 1 + 8 + 1 + 10 + 13 * 17 + 1 = 269 bytes at most.
  static constexpr std::size_t kMaxLine = 288;
  void put(char c) noexcept {
    if (n_ < kMaxLine) line_[n_++] = static_cast<std::uint8_t>(c);
  }
  void put(const char* s) noexcept {
    while (*s != '\0')
      put(*s++);
  }
  void dec(std::uint64_t v) noexcept {
    char tmp[24];
    std::size_t k = 0;
    do {
      tmp[k++] = static_cast<char>('0' + v % 10);
      v /= 10;
    } while (v != 0);
    while (k > 0)
      put(tmp[--k]);
  }
  void hex_bits(std::uint64_t bits, int digits) noexcept {
    static constexpr char kDigits[] = "0123456789abcdef";
    for (int k = 4 * (digits - 1); k >= 0; k -= 4)
      put(kDigits[(bits >> k) & 0xFu]);
  }
  void hex32(std::uint32_t v) noexcept { hex_bits(v, 8); }
  void hex64(double v) noexcept {
    std::uint64_t bits = 0;
    std::memcpy(&bits, &v, sizeof bits);
    put(' ');
    hex_bits(bits, 16);
  }

  hal::SerialPort& port_;
  std::uint8_t line_[kMaxLine]{};
  std::size_t n_{0};
  std::uint32_t emitted_{0};
  std::uint32_t failed_{0};
};

}  // namespace magvec::app
