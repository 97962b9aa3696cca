// SolveWorker: runs the calibrator's solve (Pipeline::take_solve_job) on its own thread, so that
// the acquisition thread never waits for it. The hand-over is bounded and never blocks the
// acquisition side: one job slot and one result slot. A job submitted while another waits replaces
// it (the waiting one belongs to a calibration that was superseded); results are tagged so the
// caller can drop those of an earlier session.
// The thread runs under SCHED_OTHER at a lower priority (nice 10) even when the daemon runs
// SCHED_FIFO: on a single-core computer the solve then only uses the time the samples leave.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <optional>
#include <thread>

#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

class SolveWorker {
 public:
  struct Done {
    std::uint64_t tag{0};
    SolveResult result{};
    std::uint64_t solve_us{0};  // wall time of the solve on the worker
  };

  SolveWorker();
  // Waits for a solve in progress to finish (a solve cannot be interrupted) and joins.
  ~SolveWorker();
  SolveWorker(const SolveWorker&) = delete;
  SolveWorker& operator=(const SolveWorker&) = delete;

  // Hands `job` over (never blocks on the solve). true when it replaced a job not started yet.
  bool submit(std::uint64_t tag, SolveJob job);
  // The finished result, if any.
  std::optional<Done> take_result();
  // A job is waiting or running.
  bool busy() const;

 private:
  void run();

  mutable std::mutex mutex_;
  std::condition_variable wake_;
  bool stop_{false};
  bool running_{false};
  std::optional<std::pair<std::uint64_t, SolveJob>> job_;
  std::optional<Done> result_;
  std::thread thread_;
};

}  // namespace magvec::host::daemon
