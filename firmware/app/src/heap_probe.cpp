// Deliberate heap use in place of the application, linked like magvec_app.elf (board glue,
// startup, magvec_no_heap): this target must FAIL to link. The mcu test mcu_no_heap_link_check
// builds it and expects the failure, which proves the check guarding the image fires.
#include <cstdlib>
#include <new>

#include "magvec/app/board.hpp"

namespace magvec::app {
int app_main(const char* args) noexcept {
  void* p = std::malloc(16);
  int* q = new int(args[0]);
  const int r = (p != nullptr) + *q;
  delete q;
  std::free(p);
  return r;
}
}  // namespace magvec::app
