// Counts heap allocations made by this test process: global operator new (all forms) and, outside
// sanitizer builds, malloc/calloc/realloc. Used to prove the per-sample paths never allocate.
#pragma once

#include <cstddef>

namespace magvec::test {

std::size_t heap_allocations() noexcept;  // allocations since process start
bool counts_malloc() noexcept;            // false under ASan, where only operator new is counted

// Counts allocations in a scope.
class AllocationScope {
 public:
  AllocationScope() noexcept : start_(heap_allocations()) {}
  std::size_t count() const noexcept { return heap_allocations() - start_; }

 private:
  std::size_t start_;
};

}  // namespace magvec::test
