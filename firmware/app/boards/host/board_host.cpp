// Host "board": the same application as a hosted executable (the reference run the mcu tests
// compare the emulated images with). Arguments are joined into the option string.
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <span>

#include "magvec/app/board.hpp"

namespace magvec::app {
namespace {
class StdoutPort final : public hal::SerialPort {
 public:
  hal::Status read(std::span<std::uint8_t>, std::size_t& n_read, std::uint32_t) noexcept override {
    n_read = 0;
    return hal::Status::kTimeout;
  }
  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override {
    n_written = std::fwrite(data.data(), 1, data.size(), stdout);
    return n_written == data.size() ? hal::Status::kOk : hal::Status::kBusError;
  }
};
StdoutPort g_stdout;
}  // namespace

void board_write(const char* s, std::size_t n) noexcept {
  std::fwrite(s, 1, n, stdout);
}
hal::SerialPort& board_record_port(bool /*uart*/) noexcept {
  return g_stdout;
}
const char* board_name() noexcept {
  return "host";
}
// No sample clock: the application acquires from its main loop, in the same order.
bool board_start_sample_clock(std::uint32_t, void (*)()) noexcept {
  return false;
}
void board_stop_sample_clock() noexcept {}
std::uint64_t board_time_us() noexcept {
  return 0;
}
void board_wait_for_interrupt(bool (*)()) noexcept {}
}  // namespace magvec::app

int main(int argc, char** argv) {
  char args[256] = {};
  std::size_t used = 0;
  for (int i = 1; i < argc; ++i) {
    const std::size_t len = std::strlen(argv[i]);
    if (used + len + 2 > sizeof args) break;
    if (used > 0) args[used++] = ' ';
    std::memcpy(args + used, argv[i], len);
    used += len;
  }
  const int rc = magvec::app::app_main(args);
  std::fflush(stdout);
  return rc;
}
