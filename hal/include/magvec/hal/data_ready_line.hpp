// HAL: a data-ready GPIO input that reports edges with timestamps (libgpiod line events with
// kernel timestamps on Linux, an EXTI interrupt latching a timer on an MCU, a simulated line).
#pragma once

#include <cstdint>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

enum class Edge : std::uint8_t { kRising, kFalling };

struct EdgeEvent {
  std::uint64_t t_us{0};  // when the edge happened, on the hal::Clock time base
  Edge edge{Edge::kFalling};
};

class DataReadyLine {
 public:
  // Waits up to timeout_us (0 = poll) for the next queued edge. kOk with the event, kTimeout
  // when none. Edges are queued in order; an implementation that lost edges reports it in
  // missed_edges().
  virtual Status wait_edge(EdgeEvent& out, std::uint32_t timeout_us) noexcept = 0;
  virtual std::uint32_t missed_edges() const noexcept = 0;

 protected:
  ~DataReadyLine() = default;
};

}  // namespace magvec::hal
