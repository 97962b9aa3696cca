// STM32F4 board (STM32F405/407, 16 MHz HSI after reset; build only, not run in CI): report lines
// on USART2 (PA2 TX, AF7, 115200 8N1, polled). No arguments; after the run the core sleeps.
// Registers per RM0090 (RCC 0x40023800, GPIOA 0x40020000, USART2 0x40004400).
#include <cstdint>

#include "magvec/app/board.hpp"

namespace {

constexpr std::uintptr_t kRcc = 0x40023800u;
constexpr std::uintptr_t kGpioA = 0x40020000u;
constexpr std::uintptr_t kUsart2 = 0x40004400u;
constexpr std::uint32_t kHsiHz = 16'000'000u;
constexpr std::uint32_t kBaud = 115'200u;

volatile std::uint32_t& reg(std::uintptr_t addr) noexcept {
  return *reinterpret_cast<volatile std::uint32_t*>(addr);
}

}  // namespace

namespace magvec::app {
void board_write(const char* s, std::size_t n) noexcept {
  for (std::size_t i = 0; i < n; ++i) {
    while ((reg(kUsart2 + 0x00) & (1u << 7)) == 0) {  // SR.TXE
    }
    reg(kUsart2 + 0x04) = static_cast<std::uint8_t>(s[i]);  // DR
  }
  while ((reg(kUsart2 + 0x00) & (1u << 6)) == 0) {  // SR.TC
  }
}
const char* board_name() noexcept {
  return "stm32f4";
}
}  // namespace magvec::app

extern "C" void magvec_board_early_init(void) {
  reg(kRcc + 0x30) |= 1u << 0;                     // AHB1ENR.GPIOAEN
  reg(kRcc + 0x40) |= 1u << 17;                    // APB1ENR.USART2EN
  const std::uint32_t enabled = reg(kRcc + 0x40);  // read back: clock running before use
  (void)enabled;
  // PA2: alternate function 7 (USART2_TX).
  reg(kGpioA + 0x00) = (reg(kGpioA + 0x00) & ~(3u << 4)) | (2u << 4);    // MODER2 = AF
  reg(kGpioA + 0x20) = (reg(kGpioA + 0x20) & ~(0xFu << 8)) | (7u << 8);  // AFRL2 = AF7
  reg(kUsart2 + 0x08) = (kHsiHz + kBaud / 2) / kBaud;                    // BRR (OVER8 = 0)
  reg(kUsart2 + 0x0C) = (1u << 13) | (1u << 3);                          // CR1: UE, TE
}

int main() {
  const int rc = magvec::app::app_main("");
  for (;;) {
    asm volatile("wfi");
  }
  return rc;
}
