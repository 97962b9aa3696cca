// BackgroundWorker: runs the daemon's slow jobs on their own thread, so that the acquisition thread
// never waits for them: the calibrator's solve (Pipeline::take_solve_job; SolveWorker) and the
// atomic write of the accepted calibration (temp file, fsync, rename, fsync of the directory:
// 49 ms measured in the VM test's guest, longer on an SD card; PersistWorker).
// The hand-over is bounded and never blocks the acquisition side: one job slot and one result
// slot. A job submitted while another waits replaces it (the waiting one was superseded: an
// earlier calibration); results are tagged so the caller can drop those of an earlier session.
// The thread runs under SCHED_OTHER at a lower priority (nice 10) even when the daemon runs
// SCHED_FIFO: on a single-core computer the job then only uses the time the samples leave.
// The hand-over lock inherits priority: when the acquisition thread (SCHED_FIFO) waits for it, the
// worker holding it runs at the waiter's priority until it lets go, instead of queueing behind
// every other SCHED_OTHER task of the computer (with a plain mutex, an unbounded priority
// inversion). A finished job is freed before that lock is taken.
#pragma once

#include <pthread.h>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <utility>

#include "magvec/host/daemon/persistence.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

// A mutex with the priority-inheritance protocol (PTHREAD_PRIO_INHERIT); BasicLockable, for
// std::unique_lock and std::condition_variable_any.
class PriorityInheritanceMutex {
 public:
  PriorityInheritanceMutex();
  ~PriorityInheritanceMutex();
  PriorityInheritanceMutex(const PriorityInheritanceMutex&) = delete;
  PriorityInheritanceMutex& operator=(const PriorityInheritanceMutex&) = delete;
  void lock() noexcept;
  void unlock() noexcept;

 private:
  pthread_mutex_t m_;
};

// Makes the calling thread a background one: SCHED_OTHER, nice 10 (see above).
void lower_to_background_priority() noexcept;

template <typename Result>
class BackgroundWorker {
 public:
  using Job = std::function<Result()>;
  struct Done {
    std::uint64_t tag{0};
    Result result{};
    std::uint64_t run_us{0};  // wall time of the job on the worker
  };

  BackgroundWorker() : thread_([this] { run(); }) {}
  // Waits for a job in progress to finish (a job cannot be interrupted) and joins; a job not
  // started yet is dropped.
  ~BackgroundWorker() {
    {
      std::lock_guard<PriorityInheritanceMutex> lock(mutex_);
      stop_ = true;
    }
    wake_.notify_all();
    thread_.join();
  }
  BackgroundWorker(const BackgroundWorker&) = delete;
  BackgroundWorker& operator=(const BackgroundWorker&) = delete;

  // Hands `job` over (never blocks on a job). true when it replaced a job not started yet.
  bool submit(std::uint64_t tag, Job job) {
    bool replaced = false;
    {
      std::lock_guard<PriorityInheritanceMutex> lock(mutex_);
      replaced = job_.has_value();
      job_.emplace(tag, std::move(job));
    }
    wake_.notify_all();
    return replaced;
  }
  // The finished result, if any.
  std::optional<Done> take_result() {
    std::lock_guard<PriorityInheritanceMutex> lock(mutex_);
    std::optional<Done> r = std::move(result_);
    result_.reset();
    return r;
  }
  // A job is waiting or running.
  bool busy() const {
    std::lock_guard<PriorityInheritanceMutex> lock(mutex_);
    return running_ || job_.has_value();
  }
  // Blocks until no job waits or runs (for the end of the daemon, never on the acquisition path).
  void wait_idle() {
    std::unique_lock<PriorityInheritanceMutex> lock(mutex_);
    wake_.wait(lock, [this] { return !running_ && !job_.has_value(); });
  }

 private:
  void run() {
    lower_to_background_priority();
    std::unique_lock<PriorityInheritanceMutex> lock(mutex_);
    while (true) {
      wake_.wait(lock, [this] { return stop_ || job_.has_value(); });
      if (stop_) return;
      std::pair<std::uint64_t, Job> job = std::move(*job_);
      job_.reset();
      running_ = true;
      lock.unlock();
      const auto t0 = std::chrono::steady_clock::now();
      Done d;
      d.tag = job.first;
      d.result = job.second();
      d.run_us = static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::microseconds>(
                                                std::chrono::steady_clock::now() - t0)
                                                .count());
      // What the job owns (a solve's calibrator snapshot) is freed before the lock is taken.
      job.second = nullptr;
      lock.lock();
      running_ = false;
      result_ = std::move(d);  // an unread older result is superseded
      wake_.notify_all();      // wait_idle()
    }
  }

  mutable PriorityInheritanceMutex mutex_;
  std::condition_variable_any wake_;
  bool stop_{false};
  bool running_{false};
  std::optional<std::pair<std::uint64_t, Job>> job_;
  std::optional<Done> result_;
  std::thread thread_;  // last: started once every member above exists
};

using SolveWorker = BackgroundWorker<SolveResult>;

using PersistWorker = BackgroundWorker<PersistOutcome>;

}  // namespace magvec::host::daemon
