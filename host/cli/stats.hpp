// Running statistics for CLI summaries (Welford mean/SD plus RMS), and table formatting.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <string>

namespace magvec::host::cli {

class Stats {
 public:
  void add(double x) noexcept {
    ++n_;
    const double d = x - mean_;
    mean_ += d / static_cast<double>(n_);
    m2_ += d * (x - mean_);
    sum_sq_ += x * x;
  }
  double mean() const noexcept { return mean_; }
  double sd() const noexcept { return n_ > 1 ? std::sqrt(m2_ / static_cast<double>(n_ - 1)) : 0.0; }
  double rms() const noexcept {
    return n_ > 0 ? std::sqrt(sum_sq_ / static_cast<double>(n_)) : 0.0;
  }
  std::uint64_t count() const noexcept { return n_; }

 private:
  std::uint64_t n_ = 0;
  double mean_ = 0, m2_ = 0, sum_sq_ = 0;
};

// Fixed-point number, right-aligned in 14 characters (table cells).
inline std::string num(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%14.*f", decimals, v);
  return buf;
}
// Fixed-point number without padding (prose).
inline std::string fixed(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

}  // namespace magvec::host::cli
