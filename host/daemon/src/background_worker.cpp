// BackgroundWorker's non-template parts; see background_worker.hpp.
#include "magvec/host/daemon/background_worker.hpp"

#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cstdlib>

namespace magvec::host::daemon {

PriorityInheritanceMutex::PriorityInheritanceMutex() {
  pthread_mutexattr_t a;
  pthread_mutexattr_init(&a);
  // Supported by every Linux libc (futex PI); should it fail, the mutex is a plain one: still
  // correct, only without the inheritance.
  (void)pthread_mutexattr_setprotocol(&a, PTHREAD_PRIO_INHERIT);
  if (pthread_mutex_init(&m_, &a) != 0) std::abort();
  pthread_mutexattr_destroy(&a);
}

PriorityInheritanceMutex::~PriorityInheritanceMutex() {
  pthread_mutex_destroy(&m_);
}

void PriorityInheritanceMutex::lock() noexcept {
  (void)pthread_mutex_lock(&m_);  // fails only on misuse (a default-type mutex locked twice)
}

void PriorityInheritanceMutex::unlock() noexcept {
  (void)pthread_mutex_unlock(&m_);
}

void lower_to_background_priority() noexcept {
  // A thread inherits its creator's policy; a background job must never preempt the acquisition.
  sched_param sp{};
  (void)pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
  (void)setpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid)), 10);
}

}  // namespace magvec::host::daemon
