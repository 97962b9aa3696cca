// ScalarAligner: gives each magnetometer sample the total field F of a scalar magnetometer at
// the sample's own time, for calibration and held-out validation (the F the pipeline takes with
// each sample, DevicePipeline::on_magnetometer's f_ref_nT).
//
// A scalar instrument reads at its own, slower cadence (a G-882 at 10 Hz against a fluxgate at
// 100-1000 Hz) and its reading of time t arrives after the fluxgate samples of t. So, as the
// core's fusion horizon does for the INS, a magnetometer sample waits in a bounded queue until a
// scalar reading at or after its time has arrived; then its F is interpolated linearly between
// the two readings around it (readings at most max_gap_us apart). A sample is released without
// that bracket when a magnetometer sample horizon_us newer arrives, the queue is full or the
// stream ends; it then takes the nearest reading within max_distance_us, else the fallback
// (the configured constant reference F, or NaN: none, the calibrator skips it). Readings flagged
// invalid (low signal), non-finite or older than the newest one are counted and not used.
// The order of the magnetometer samples is kept. Header-only, fixed memory, noexcept, no heap:
// it includes only the HAL interfaces (usable in the MCU image).
#pragma once

#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/scalar_source.hpp"

namespace magvec::pipeline {

struct ScalarAlignerConfig {
  std::uint32_t max_gap_us{250'000};       // interpolate only across a gap of at most this
  std::uint32_t max_distance_us{150'000};  // otherwise the nearest reading within this
  std::uint32_t horizon_us{300'000};       // a sample waits at most this (magnetometer time)
  double fallback_nT{std::numeric_limits<double>::quiet_NaN()};
};

struct ScalarAlignerCounters {
  std::uint64_t readings{0};      // scalar readings accepted
  std::uint64_t invalid{0};       // flagged (kScalarInvalidMask) or non-finite: not used
  std::uint64_t reordered{0};     // not newer than the newest accepted one: not used
  std::uint64_t interpolated{0};  // samples whose F was interpolated between two readings
  std::uint64_t nearest{0};       // samples that took the nearest reading
  std::uint64_t fallback{0};      // samples that took the fallback (no reading close enough)
  std::uint64_t expired{0};       // samples released by the horizon, a full queue or the end
};

template <std::size_t ReadingCapacity = 64, std::size_t QueueCapacity = 1024>
class ScalarAligner {
  static_assert(ReadingCapacity >= 2 && QueueCapacity >= 1);

 public:
  explicit ScalarAligner(const ScalarAlignerConfig& config = {}) noexcept : config_(config) {}

  // Emit: emit(const hal::MagnetometerSample&, double f_nT), called in sample order.
  template <typename Emit>
  void on_scalar(const hal::ScalarSample& r, Emit&& emit) noexcept {
    if ((r.flags & hal::kScalarInvalidMask) != 0 || !std::isfinite(r.f_nT)) {
      ++counters_.invalid;
      return;
    }
    if (n_readings_ > 0 && r.t_us <= reading(n_readings_ - 1).t_us) {
      ++counters_.reordered;
      return;
    }
    if (n_readings_ == ReadingCapacity) {
      first_reading_ = (first_reading_ + 1) % ReadingCapacity;
      --n_readings_;
    }
    readings_[(first_reading_ + n_readings_) % ReadingCapacity] = Reading{r.t_us, r.f_nT};
    ++n_readings_;
    ++counters_.readings;
    release(emit, false);
  }

  template <typename Emit>
  void on_magnetometer(const hal::MagnetometerSample& s, Emit&& emit) noexcept {
    if (n_queued_ == QueueCapacity) release_front(emit, true);
    queue_[(first_queued_ + n_queued_) % QueueCapacity] = s;
    ++n_queued_;
    newest_mag_t_us_ = s.t_us;
    release(emit, false);
  }

  // Releases every waiting sample (end of the stream).
  template <typename Emit>
  void flush(Emit&& emit) noexcept {
    release(emit, true);
  }

  // F at t_us from the readings held now (also what a released sample got).
  double f_at(std::uint64_t t_us) const noexcept { return lookup(t_us, nullptr); }

  std::size_t queued() const noexcept { return n_queued_; }
  const ScalarAlignerCounters& counters() const noexcept { return counters_; }
  const ScalarAlignerConfig& config() const noexcept { return config_; }

 private:
  struct Reading {
    std::uint64_t t_us{0};
    double f_nT{0};
  };
  enum class How : std::uint8_t { kInterpolated, kNearest, kFallback };

  const Reading& reading(std::size_t i) const noexcept {
    return readings_[(first_reading_ + i) % ReadingCapacity];
  }

  static std::uint64_t distance(std::uint64_t a, std::uint64_t b) noexcept {
    return a > b ? a - b : b - a;
  }

  double lookup(std::uint64_t t_us, How* how) const noexcept {
    How h = How::kFallback;
    double f = config_.fallback_nT;
    std::uint64_t best = std::numeric_limits<std::uint64_t>::max();
    for (std::size_t i = n_readings_; i-- > 0;) {
      const Reading& r = reading(i);
      if (r.t_us <= t_us && i + 1 < n_readings_) {
        const Reading& next = reading(i + 1);
        if (next.t_us - r.t_us <= config_.max_gap_us) {
          const double w =
              static_cast<double>(t_us - r.t_us) / static_cast<double>(next.t_us - r.t_us);
          f = r.f_nT + w * (next.f_nT - r.f_nT);
          h = How::kInterpolated;
          break;
        }
      }
      const std::uint64_t d = distance(r.t_us, t_us);
      if (d <= config_.max_distance_us && d < best) {
        best = d;
        f = r.f_nT;
        h = How::kNearest;
      }
      if (r.t_us <= t_us) break;  // older readings are farther away
    }
    if (how != nullptr) *how = h;
    return f;
  }

  template <typename Emit>
  void release_front(Emit& emit, bool forced) noexcept {
    const hal::MagnetometerSample s = queue_[first_queued_];
    first_queued_ = (first_queued_ + 1) % QueueCapacity;
    --n_queued_;
    if (forced) ++counters_.expired;
    How how = How::kFallback;
    const double f = lookup(s.t_us, &how);
    switch (how) {
      case How::kInterpolated:
        ++counters_.interpolated;
        break;
      case How::kNearest:
        ++counters_.nearest;
        break;
      case How::kFallback:
        ++counters_.fallback;
        break;
    }
    emit(s, f);
  }

  template <typename Emit>
  void release(Emit& emit, bool all) noexcept {
    while (n_queued_ > 0) {
      const hal::MagnetometerSample& front = queue_[first_queued_];
      const bool bracketed = n_readings_ > 0 && reading(n_readings_ - 1).t_us >= front.t_us;
      const bool expired =
          newest_mag_t_us_ > front.t_us && newest_mag_t_us_ - front.t_us > config_.horizon_us;
      if (!bracketed && !expired && !all) return;
      release_front(emit, !bracketed);
    }
  }

  ScalarAlignerConfig config_;
  ScalarAlignerCounters counters_{};
  std::array<Reading, ReadingCapacity> readings_{};
  std::size_t first_reading_{0};
  std::size_t n_readings_{0};
  std::array<hal::MagnetometerSample, QueueCapacity> queue_{};
  std::size_t first_queued_{0};
  std::size_t n_queued_{0};
  std::uint64_t newest_mag_t_us_{0};
};

}  // namespace magvec::pipeline
