// Linux transports: libgpiod 1.6 (v1 API) data-ready line with kernel event timestamps.
#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"

#include <gpiod.h>

#include <cerrno>

#include "magvec/drivers/linux/linux_clock.hpp"

namespace magvec::drivers {
namespace {

std::string line_name(const GpiodConfig& c) {
  return "gpiod " + c.chip + " line " + std::to_string(c.line);
}

}  // namespace

std::unique_ptr<GpiodDataReadyLine> GpiodDataReadyLine::open(const GpiodConfig& config,
                                                             OsError* err) {
  const std::string name = line_name(config);
  errno = 0;
  gpiod_chip* chip = ::gpiod_chip_open_lookup(config.chip.c_str());
  if (chip == nullptr) {
    const int e = errno != 0 ? errno : ENOENT;
    report_error(err, make_os_error(name, "open chip (no such GPIO chip?)", e));
    return nullptr;
  }
  const unsigned n_lines = ::gpiod_chip_num_lines(chip);
  if (config.line >= n_lines) {
    ::gpiod_chip_close(chip);
    report_error(
        err,
        make_error(name, "get line",
                   "no such line (the chip has " + std::to_string(n_lines) + " lines)", EINVAL));
    return nullptr;
  }
  gpiod_line* line = ::gpiod_chip_get_line(chip, config.line);
  if (line == nullptr) {
    const int e = errno;
    ::gpiod_chip_close(chip);
    report_error(err, make_os_error(name, "get line", e));
    return nullptr;
  }
  int rc = 0;
  if (config.both_edges) {
    rc = ::gpiod_line_request_both_edges_events(line, config.consumer.c_str());
  } else if (config.edge == hal::Edge::kRising) {
    rc = ::gpiod_line_request_rising_edge_events(line, config.consumer.c_str());
  } else {
    rc = ::gpiod_line_request_falling_edge_events(line, config.consumer.c_str());
  }
  if (rc < 0) {
    const int e = errno;
    ::gpiod_chip_close(chip);
    report_error(err,
                 make_os_error(name,
                               e == EBUSY ? "request edge events (line used by another consumer?)"
                                          : "request edge events",
                               e));
    return nullptr;
  }
  return std::unique_ptr<GpiodDataReadyLine>(new GpiodDataReadyLine(chip, line, config));
}

GpiodDataReadyLine::GpiodDataReadyLine(gpiod_chip* chip, gpiod_line* line, GpiodConfig config)
    : chip_(chip), line_(line), config_(std::move(config)), name_(line_name(config_)) {}

GpiodDataReadyLine::~GpiodDataReadyLine() {
  if (line_ != nullptr) ::gpiod_line_release(line_);
  if (chip_ != nullptr) ::gpiod_chip_close(chip_);
}

hal::Status GpiodDataReadyLine::wait_edge(hal::EdgeEvent& out, std::uint32_t timeout_us) noexcept {
  const timespec ts = timespec_from_us(timeout_us);
  int rc = 0;
  do {
    rc = ::gpiod_line_event_wait(line_, &ts);
  } while (rc < 0 && errno == EINTR);
  if (rc < 0) {
    assign_os_error(last_error_, name_, "wait for event", errno);
    return hal::Status::kBusError;
  }
  if (rc == 0) return hal::Status::kTimeout;
  gpiod_line_event ev{};
  if (::gpiod_line_event_read(line_, &ev) < 0) {
    assign_os_error(last_error_, name_, "read event", errno);
    return hal::Status::kBusError;
  }
  out.t_us = kernel_event_to_monotonic_us(ev.ts);
  out.edge =
      ev.event_type == GPIOD_LINE_EVENT_RISING_EDGE ? hal::Edge::kRising : hal::Edge::kFalling;
  // With both edges requested they must alternate; a repeated direction means the kernel's
  // event queue overflowed (the v1 uAPI drops events silently) and at least one pair was lost.
  if (config_.both_edges && have_last_ && out.edge == last_edge_) ++missed_edges_;
  have_last_ = true;
  last_edge_ = out.edge;
  ++events_;
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
