// Replacement global allocation functions that count every allocation of the test process.
#include "support/alloc_counter.hpp"

#include <atomic>
#include <cstdlib>
#include <new>

// ASan owns malloc: interposing on it runs before the runtime is initialised. GCC says so with
// __SANITIZE_ADDRESS__, clang with __has_feature(address_sanitizer).
#if defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MAGVEC_ASAN 1
#endif
#endif
#if defined(__SANITIZE_ADDRESS__) || defined(MAGVEC_ASAN)
#define MAGVEC_COUNT_MALLOC 0
#else
#define MAGVEC_COUNT_MALLOC 1
#endif

namespace {
std::atomic<std::size_t> g_allocations{0};
}

#if MAGVEC_COUNT_MALLOC
// glibc exports its allocator under these names; defining malloc here interposes on every call in
// the process (including the C++ runtime's operator new).
extern "C" void* __libc_malloc(std::size_t);
extern "C" void* __libc_calloc(std::size_t, std::size_t);
extern "C" void* __libc_realloc(void*, std::size_t);

extern "C" void* malloc(std::size_t n) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  return __libc_malloc(n);
}
extern "C" void* calloc(std::size_t n, std::size_t s) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  return __libc_calloc(n, s);
}
extern "C" void* realloc(void* p, std::size_t n) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  return __libc_realloc(p, n);
}
#endif

namespace {
void* counted_new(std::size_t n) {
#if !MAGVEC_COUNT_MALLOC
  g_allocations.fetch_add(1, std::memory_order_relaxed);
#endif
  if (n == 0) n = 1;
  void* p = std::malloc(n);
  if (p == nullptr) throw std::bad_alloc();
  return p;
}
void* counted_new_aligned(std::size_t n, std::align_val_t al) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);  // aligned_alloc bypasses malloc
  const std::size_t a = static_cast<std::size_t>(al);
  void* p = std::aligned_alloc(a, ((n + a - 1) / a) * a);
  if (p == nullptr) throw std::bad_alloc();
  return p;
}
}  // namespace

void* operator new(std::size_t n) {
  return counted_new(n);
}
void* operator new[](std::size_t n) {
  return counted_new(n);
}
void* operator new(std::size_t n, const std::nothrow_t&) noexcept {
  try {
    return counted_new(n);
  } catch (...) {
    return nullptr;
  }
}
void* operator new[](std::size_t n, const std::nothrow_t&) noexcept {
  try {
    return counted_new(n);
  } catch (...) {
    return nullptr;
  }
}
void* operator new(std::size_t n, std::align_val_t al) {
  return counted_new_aligned(n, al);
}
void* operator new[](std::size_t n, std::align_val_t al) {
  return counted_new_aligned(n, al);
}
void operator delete(void* p) noexcept {
  std::free(p);
}
void operator delete[](void* p) noexcept {
  std::free(p);
}
void operator delete(void* p, std::size_t) noexcept {
  std::free(p);
}
void operator delete[](void* p, std::size_t) noexcept {
  std::free(p);
}
void operator delete(void* p, std::align_val_t) noexcept {
  std::free(p);
}
void operator delete[](void* p, std::align_val_t) noexcept {
  std::free(p);
}
void operator delete(void* p, std::size_t, std::align_val_t) noexcept {
  std::free(p);
}
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept {
  std::free(p);
}

namespace magvec::test {
std::size_t heap_allocations() noexcept {
  return g_allocations.load(std::memory_order_relaxed);
}
bool counts_malloc() noexcept {
  return MAGVEC_COUNT_MALLOC != 0;
}
}  // namespace magvec::test
