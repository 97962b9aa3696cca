// SolveWorker; see solve_worker.hpp.
#include "magvec/host/daemon/solve_worker.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <chrono>
#include <utility>

namespace magvec::host::daemon {

SolveWorker::SolveWorker() : thread_([this] { run(); }) {}

SolveWorker::~SolveWorker() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  thread_.join();
}

bool SolveWorker::submit(std::uint64_t tag, SolveJob job) {
  bool replaced = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    replaced = job_.has_value();
    job_.emplace(tag, std::move(job));
  }
  wake_.notify_one();
  return replaced;
}

std::optional<SolveWorker::Done> SolveWorker::take_result() {
  std::lock_guard<std::mutex> lock(mutex_);
  std::optional<Done> r = std::move(result_);
  result_.reset();
  return r;
}

bool SolveWorker::busy() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return running_ || job_.has_value();
}

void SolveWorker::run() {
  // A thread inherits its creator's policy; the solve must never preempt the acquisition thread.
  sched_param sp{};
  (void)pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
  (void)setpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid)), 10);
  std::unique_lock<std::mutex> lock(mutex_);
  while (true) {
    wake_.wait(lock, [this] { return stop_ || job_.has_value(); });
    if (stop_) return;
    auto [tag, job] = std::move(*job_);
    job_.reset();
    running_ = true;
    lock.unlock();
    const auto t0 = std::chrono::steady_clock::now();
    Done d;
    d.tag = tag;
    d.result = job();
    d.solve_us = static_cast<std::uint64_t>(
        std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::steady_clock::now() - t0)
            .count());
    lock.lock();
    running_ = false;
    result_ = std::move(d);  // an unread older result is superseded
  }
}

}  // namespace magvec::host::daemon
