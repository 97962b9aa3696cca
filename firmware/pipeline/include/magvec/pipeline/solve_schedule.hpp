// SolveSchedule: when the result of a solve run off the per-sample path goes back into the loop
// (core::SensorLoop with LoopConfig::external_solve; sensor_loop.hpp, docs/architecture.md).
//
// Rule (DECISION): the loop raises a solve ticket while processing record k (1-based count of the
// records the pipeline emitted); the solve may run at any time after that (the MCU image: in the
// main loop's idle time, preempted by acquisition); its result is installed when record
// k + install_after_records is emitted, and if it has not run by then it runs there. The
// calibrator's data are frozen while the loop solves, so the candidate does not depend on when
// the solve ran, and with a fixed install record neither do the records: the MCU image, its host
// twin and `magvec run` with the image's profile emit the same records whatever their CPUs'
// speeds. (magvecd installs as soon as its worker is done instead: on a real-time device that is
// what lets the held-out validation start earliest.)
// Header-only, noexcept, no heap; it may include only the core.
#pragma once

#include <cstdint>

#include "magvec/core/sensor_loop.hpp"

namespace magvec::pipeline {

class SolveSchedule {
 public:
  explicit SolveSchedule(std::uint32_t install_after_records) noexcept
      : install_after_(install_after_records) {}

  // After the loop emitted record number `record`: true when it has raised a ticket not seen
  // before (a solve is wanted now).
  template <typename Loop>
  bool raised(const Loop& loop, std::uint32_t record) noexcept {
    if (loop.state() != core::CalState::kSolving || loop.solve_ticket() == ticket_) return false;
    pending_ = true;
    ticket_ = loop.solve_ticket();
    ticket_record_ = record;
    return true;
  }

  // The pending ticket's result is due with this record.
  bool due(std::uint32_t record) const noexcept {
    return pending_ && record - ticket_record_ >= install_after_;
  }
  // The result went in (or was refused as stale): nothing pending.
  void installed() noexcept { pending_ = false; }

  bool pending() const noexcept { return pending_; }
  std::uint32_t ticket() const noexcept { return ticket_; }
  std::uint32_t ticket_record() const noexcept { return ticket_record_; }
  std::uint32_t install_after_records() const noexcept { return install_after_; }

 private:
  std::uint32_t install_after_;
  bool pending_{false};
  std::uint32_t ticket_{0};
  std::uint32_t ticket_record_{0};
};

}  // namespace magvec::pipeline
