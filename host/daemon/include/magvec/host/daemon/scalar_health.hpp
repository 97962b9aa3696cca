// What magvecd reports of its scalar magnetometer in the health message: the source's counters
// (hal::ScalarCounters), the reads that failed, the silences and how each magnetometer sample got
// its F (pipeline::ScalarAligner). Plain numbers, so that the LCM conversion needs no device.
#pragma once

#include <cstdint>

#include "magvec/hal/scalar_source.hpp"

namespace magvec::host::daemon {

struct ScalarHealth {
  hal::ScalarCounters source{};
  std::uint64_t read_errors{0};     // reads that returned a rejected line or a transport failure
  std::uint64_t timeouts{0};        // silences of the aligner's max_gap_us without a reading
  std::uint64_t f_interpolated{0};  // samples whose F was interpolated between two readings
  std::uint64_t f_nearest{0};       // samples that took the nearest reading
  std::uint64_t f_fallback{0};      // samples without a reading near them
};

}  // namespace magvec::host::daemon
