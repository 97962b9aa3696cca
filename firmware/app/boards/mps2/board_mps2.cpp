// qemu mps2-an386 (Cortex-M4F) / mps2-an500 (Cortex-M7) board: ARM semihosting done here (the
// equivalent of newlib's initialise_monitor_handles + _write + _exit, ~30 lines) because
// librdimon's syscalls pull in newlib's stdio initialisation, which references malloc, and the
// image links no heap. Output: SYS_WRITE to the ":tt" console handle; arguments: SYS_GET_CMDLINE
// (qemu: -semihosting-config ...,arg=<prog>,arg=<option>..., or -kernel/-append); exit code back
// to qemu through SYS_EXIT_EXTENDED (main's return value becomes qemu's exit status).
// Records (option `uart`): CMSDK UART0, polled (mmio_uart.hpp), qemu's first -serial backend.
#include <cstdint>
#include <cstring>

#include "magvec/app/board.hpp"
#include "magvec/app/mmio_uart.hpp"
#include "magvec/app/systick.hpp"

namespace {

constexpr std::uint32_t kSysOpen = 0x01;
constexpr std::uint32_t kSysWrite = 0x05;
constexpr std::uint32_t kSysGetCmdline = 0x15;
constexpr std::uint32_t kSysExitExtended = 0x20;
constexpr std::uint32_t kAdpStoppedApplicationExit = 0x20026;
constexpr std::uint32_t kOpenModeWrite = 4;  // "w"

// One ARM semihosting call (Thumb: BKPT 0xAB, r0 = operation, r1 = parameter block).
std::int32_t semihost(std::uint32_t op, const void* block) noexcept {
  register std::uint32_t r0 asm("r0") = op;
  register const void* r1 asm("r1") = block;
  asm volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
  return static_cast<std::int32_t>(r0);
}

std::uint32_t word(const void* p) noexcept {
  return static_cast<std::uint32_t>(reinterpret_cast<std::uintptr_t>(p));
}

std::int32_t g_console = -1;
char g_cmdline[256];

// The semihosting console as a byte stream (records under qemu by default).
class SemihostingPort final : public magvec::hal::SerialPort {
 public:
  magvec::hal::Status read(std::span<std::uint8_t>, std::size_t& n_read,
                           std::uint32_t) noexcept override {
    n_read = 0;
    return magvec::hal::Status::kTimeout;
  }
  magvec::hal::Status write(std::span<const std::uint8_t> data,
                            std::size_t& n_written) noexcept override {
    n_written = 0;
    if (g_console < 0) return magvec::hal::Status::kNotReady;
    const std::uint32_t block[3] = {static_cast<std::uint32_t>(g_console), word(data.data()),
                                    static_cast<std::uint32_t>(data.size())};
    const std::int32_t left = semihost(kSysWrite, block);  // bytes NOT written
    n_written = data.size() - static_cast<std::size_t>(left > 0 ? left : 0);
    return left == 0 ? magvec::hal::Status::kOk : magvec::hal::Status::kBusError;
  }
};

SemihostingPort g_semihosting;
constinit magvec::app::CmsdkUart g_uart0(magvec::app::CmsdkUart::kMps2Uart0);
// qemu's mps2 boards feed SysTick's reference clock input at 1 MHz: one count per microsecond.
constexpr std::uint32_t kRefClkCountsPerUs = 1;
magvec::app::SysTickClock g_clock;

}  // namespace

namespace magvec::app {
void board_write(const char* s, std::size_t n) noexcept {
  if (g_console < 0) return;
  const std::uint32_t block[3] = {static_cast<std::uint32_t>(g_console), word(s),
                                  static_cast<std::uint32_t>(n)};
  (void)semihost(kSysWrite, block);  // returns the number of bytes NOT written
}
hal::SerialPort& board_record_port(bool uart) noexcept {
  if (uart) return g_uart0;
  return g_semihosting;
}
const char* board_name() noexcept {
  return MAGVEC_BOARD_NAME;
}
bool board_start_sample_clock(std::uint32_t period_us, void (*tick)()) noexcept {
  return g_clock.start(period_us, kRefClkCountsPerUs, false, tick);
}
void board_stop_sample_clock() noexcept {
  g_clock.stop();
}
std::uint64_t board_time_us() noexcept {
  return g_clock.time_us();
}
void board_wait_for_interrupt(bool (*idle)()) noexcept {
  wait_for_interrupt_unless_busy(idle);
}
}  // namespace magvec::app

extern "C" void SysTick_Handler(void) {
  g_clock.on_interrupt();
}

extern "C" void magvec_board_early_init(void) {
  static const char kTt[] = ":tt";
  const std::uint32_t block[3] = {word(kTt), kOpenModeWrite, sizeof kTt - 1};
  g_console = semihost(kSysOpen, block);
  g_uart0.init(magvec::app::CmsdkUart::kMps2PclkHz, 115'200u);
}

extern "C" [[noreturn]] void _exit(int status) {
  const std::uint32_t block[2] = {kAdpStoppedApplicationExit, static_cast<std::uint32_t>(status)};
  for (;;)
    (void)semihost(kSysExitExtended, block);
}

// Any fault or unexpected interrupt ends the emulation with a distinctive exit code.
extern "C" void magvec_board_fault(std::uint32_t ipsr) {
  (void)ipsr;
  _exit(99);
}

int main() {
  const std::uint32_t block[2] = {word(g_cmdline), sizeof g_cmdline - 1};
  const char* args = "";
  if (semihost(kSysGetCmdline, block) == 0) {
    g_cmdline[sizeof g_cmdline - 1] = '\0';
    args = g_cmdline;  // the first word is the program name
    while (*args != '\0' && *args != ' ')
      ++args;
  }
  return magvec::app::app_main(args);
}
