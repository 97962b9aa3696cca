// Deliberate heap use in place of the application, linked like magvec_app.elf (board glue,
// startup, magvec_no_heap): this target must FAIL to link. The mcu test mcu_no_heap_link_check
// builds it and expects the failure, which proves the check guarding the image fires.
#include <cstdlib>
#include <new>

#include "magvec/app/board.hpp"

namespace {
// Escaping through volatile globals: the compiler may not elide the allocations.
void* volatile g_block = nullptr;
int* volatile g_object = nullptr;
}  // namespace

namespace magvec::app {
int app_main(const char* args) noexcept {
  g_block = std::malloc(16);
  g_object = new int(args[0]);
  return g_block != nullptr && g_object != nullptr ? 0 : 1;
}
}  // namespace magvec::app
