// HAL: a source of INS attitude samples already converted to the core convention
// (docs/conventions.md: ENU navigation frame, INS body Right-Forward-Up, passive R_bn,
// h_b = R_bn h_n). The quaternion q_nb is the one of frames.hpp r_bn_from_quat: it rotates body
// vectors into ENU, so R_bn = R(q_nb)^T.
#pragma once

#include <array>
#include <cstdint>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

enum AttitudeFlag : std::uint32_t {
  kAttAttitudeValid = 1u << 0,  // INS declares roll/pitch valid
  kAttHeadingValid = 1u << 1,   // INS declares heading valid
  kAttStatusKnown = 1u << 2,    // a status message has been received (else validity unknown)
  kAttAccuracyKnown = 1u << 3,  // sigma_rad holds a reported accuracy
};

struct AttitudeSample {
  std::uint64_t t_us{0};                   // validity time on the hal::Clock time base
  std::uint64_t t_ins_us{0};               // validity time on the INS clock (as reported)
  std::array<double, 4> q_nb{1, 0, 0, 0};  // unit quaternion (w, x, y, z), body RFU -> ENU
  std::array<double, 3> sigma_rad{};       // 1-sigma roll, pitch, yaw accuracy (rad)
  std::uint32_t flags{0};                  // AttitudeFlag bits
  std::uint8_t solution_mode{0};           // INS-specific solution mode (SBG: 0..4)
};

struct AttitudeCounters {
  std::uint32_t samples{0};       // attitude samples delivered
  std::uint32_t malformed{0};     // frames with a wrong length or out-of-range content
  std::uint32_t missing_time{0};  // attitude frames without a matching time frame
  std::uint32_t ignored{0};       // frames with an ID the decoder does not use
  std::uint32_t duplicates{0};    // frames or epochs received twice, dropped
  std::uint32_t bus_errors{0};
};

class AttitudeSource {
 public:
  // Same contract as MagnetometerSource::read.
  virtual Status read(AttitudeSample& out, std::uint32_t timeout_us) noexcept = 0;
  virtual const AttitudeCounters& counters() const noexcept = 0;

 protected:
  ~AttitudeSource() = default;
};

}  // namespace magvec::hal
