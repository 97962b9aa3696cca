// HAL: where the SensorLoop sends one OutputRecord per magnetometer sample (LCM publisher, CSV
// writer, UART telemetry, test recorder). Values in nT; t_us on the hal::Clock time base.
#pragma once

#include <array>
#include <cstdint>
#include <limits>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

struct OutputRecord {
  std::uint64_t t_us{0};
  std::array<double, 3> raw_nT{};  // magnetometer reading as delivered by the source
  std::array<double, 3> h_s_nT{};  // compensated, orthogonal sensor frame
  double f_nT{0};                  // |h_s|, calibrated total field
  double sigma_f_nT{0};            // 1-sigma of f_nT from the active calibration
  std::array<double, 3> h_n_nT{};  // East, North, Up; valid only with the attitude flag set
  // 1-sigma per E/N/U component from the active calibration (NaN when h_n is not an E/N/U
  // estimate: no attitude, or the calibration is not aligned to the INS).
  double sigma_enu_nT{std::numeric_limits<double>::quiet_NaN()};
  std::uint32_t flags{0};   // defined by the SensorLoop (attitude valid, rejected, ...)
  std::uint32_t cal_id{0};  // identifier of the calibration that produced h_s
};

class RecordSink {
 public:
  virtual Status emit(const OutputRecord& record) noexcept = 0;

 protected:
  ~RecordSink() = default;
};

}  // namespace magvec::hal
