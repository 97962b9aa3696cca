// STM32F4 board (STM32F405/407, 16 MHz HSI after reset; build only, not run in CI): report lines
// and output records on USART2 (PA2 TX / PA3 RX, AF7, 115200 8N1, polled: mmio_uart.hpp). No
// arguments; after the run the core sleeps.
// Registers per RM0090 (RCC 0x40023800, GPIOA 0x40020000, USART2 0x40004400).
#include <cstdint>
#include <span>

#include "magvec/app/board.hpp"
#include "magvec/app/mmio_uart.hpp"
#include "magvec/app/systick.hpp"

namespace {

constexpr std::uintptr_t kRcc = 0x40023800u;
constexpr std::uintptr_t kGpioA = 0x40020000u;
constexpr std::uint32_t kHsiHz = 16'000'000u;  // APB1 = HSI after reset (no PLL set up)
constexpr std::uint32_t kBaud = 115'200u;

constinit magvec::app::Stm32Usart g_usart2(magvec::app::Stm32Usart::kUsart2);
magvec::app::SysTickClock g_clock;  // on the processor clock (HSI, 16 counts per microsecond)

}  // namespace

namespace magvec::app {
void board_write(const char* s, std::size_t n) noexcept {
  std::size_t written = 0;
  (void)g_usart2.write(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(s), n),
                       written);
}
hal::SerialPort& board_record_port(bool /*uart*/) noexcept {
  return g_usart2;
}
const char* board_name() noexcept {
  return "stm32f4";
}
bool board_start_sample_clock(std::uint32_t period_us, void (*tick)()) noexcept {
  return g_clock.start(period_us, kHsiHz / 1'000'000u, true, tick);
}
void board_stop_sample_clock() noexcept {
  g_clock.stop();
}
std::uint64_t board_time_us() noexcept {
  return g_clock.time_us();
}
void board_wait_for_interrupt(bool (*idle)()) noexcept {
  magvec::app::wait_for_interrupt_unless_busy(idle);
}
}  // namespace magvec::app

extern "C" void SysTick_Handler(void) {
  g_clock.on_interrupt();
}

extern "C" void magvec_board_early_init(void) {
  using magvec::app::mmio32;
  mmio32(kRcc + 0x30) |= 1u << 0;                     // AHB1ENR.GPIOAEN
  mmio32(kRcc + 0x40) |= 1u << 17;                    // APB1ENR.USART2EN
  const std::uint32_t enabled = mmio32(kRcc + 0x40);  // read back: clock running before use
  (void)enabled;
  // PA2 (TX), PA3 (RX): alternate function 7 (USART2).
  mmio32(kGpioA + 0x00) = (mmio32(kGpioA + 0x00) & ~(0xFu << 4)) | (0xAu << 4);    // MODER2/3 = AF
  mmio32(kGpioA + 0x20) = (mmio32(kGpioA + 0x20) & ~(0xFFu << 8)) | (0x77u << 8);  // AFRL2/3 = AF7
  g_usart2.init(kHsiHz, kBaud);
}

int main() {
  const int rc = magvec::app::app_main("");
  for (;;) {
    asm volatile("wfi");
  }
  return rc;
}
