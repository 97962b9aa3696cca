// Linux transports: hal::DataReadyLine over libgpiod 1.6 (GPIO character device, v1 uAPI).
// The line is requested for edge events (falling, rising or both); each event carries the
// kernel's timestamp taken in the interrupt handler, converted onto the CLOCK_MONOTONIC base
// (CLOCK_MONOTONIC since Linux 5.7, CLOCK_REALTIME before; see kernel_event_to_monotonic_us).
// The kernel queues up to 16 events per line; the v1 uAPI does not report overflow, so lost edges
// are detected only with both_edges (two consecutive edges of the same direction = at least one
// edge of the other direction lost), counted in missed_edges(), one per repeated direction.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "magvec/drivers/linux/linux_error.hpp"
#include "magvec/hal/data_ready_line.hpp"

struct gpiod_chip;
struct gpiod_line;

namespace magvec::drivers {

struct GpiodConfig {
  std::string chip{"gpiochip0"};  // name, path (/dev/gpiochipN), label or number
  unsigned line{0};               // line offset on the chip
  hal::Edge edge{hal::Edge::kFalling};
  bool both_edges{false};  // request both edges (edge is then ignored)
  std::string consumer{"magvecd"};
};

class GpiodDataReadyLine final : public hal::DataReadyLine {
 public:
  // nullptr and *err when the chip or line does not exist or the line is busy.
  static std::unique_ptr<GpiodDataReadyLine> open(const GpiodConfig& config, OsError* err);
  ~GpiodDataReadyLine();
  GpiodDataReadyLine(const GpiodDataReadyLine&) = delete;
  GpiodDataReadyLine& operator=(const GpiodDataReadyLine&) = delete;

  // kOk with the event, kTimeout, kBusError (see last_error()).
  hal::Status wait_edge(hal::EdgeEvent& out, std::uint32_t timeout_us) noexcept override;
  std::uint32_t missed_edges() const noexcept override { return missed_edges_; }

  std::uint32_t events() const noexcept { return events_; }
  const OsError& last_error() const noexcept { return last_error_; }
  const GpiodConfig& config() const noexcept { return config_; }

 private:
  GpiodDataReadyLine(gpiod_chip* chip, gpiod_line* line, GpiodConfig config);

  gpiod_chip* chip_{nullptr};
  gpiod_line* line_{nullptr};
  GpiodConfig config_;
  std::string name_;  // "gpiod <chip> line <n>", for messages
  OsError last_error_;
  std::uint32_t events_{0};
  std::uint32_t missed_edges_{0};
  bool have_last_{false};
  hal::Edge last_edge_{hal::Edge::kFalling};
};

}  // namespace magvec::drivers
