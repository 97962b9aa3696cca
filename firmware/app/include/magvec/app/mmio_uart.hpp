// Memory-mapped UARTs of the firmware boards as hal::SerialPort, polled (no interrupts, no DMA):
//   CmsdkUart  ARM CMSDK APB UART (mps2-an386/an500 UART0 at 0x40004000; qemu connects it to the
//              first -serial backend, e.g. -serial file:records.txt). Registers per the Cortex-M
//              System Design Kit TRM: DATA 0x00, STATE 0x04 (bit0 TX full, bit1 RX full), CTRL 0x08
//              (bit0 TX enable, bit1 RX enable), BAUDDIV 0x10 (>= 16).
//   Stm32Usart STM32F4 USART (RM0090 section 30.6): SR 0x00 (bit5 RXNE, bit6 TC, bit7 TXE),
//              DR 0x04, BRR 0x08, CR1 0x0C (bit2 RE, bit3 TE, bit13 UE). Pins and clocks are the
//              board's job (board_stm32f4.cpp).
// The constructors are constexpr so that a board's UART object is constant-initialised (declare it
// constinit): the boards initialise their UART in magvec_board_early_init, which runs before the
// C++ dynamic initialisers; a dynamically initialised object would still have base 0 there.
// write() blocks until every byte is in the transmitter (a record line at 115200 Bd is ~10 ms: the
// caller decimates); read() returns what the receive register holds, never waits (timeout 0).
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/serial_port.hpp"

namespace magvec::app {

inline volatile std::uint32_t& mmio32(std::uintptr_t addr) noexcept {
  return *reinterpret_cast<volatile std::uint32_t*>(addr);
}

class CmsdkUart final : public hal::SerialPort {
 public:
  static constexpr std::uintptr_t kMps2Uart0 = 0x40004000u;
  static constexpr std::uint32_t kMps2PclkHz = 25'000'000u;  // mps2 APB clock

  constexpr explicit CmsdkUart(std::uintptr_t base) noexcept : base_(base) {}

  void init(std::uint32_t pclk_hz, std::uint32_t baud) noexcept {
    std::uint32_t div = pclk_hz / baud;
    if (div < 16) div = 16;
    mmio32(base_ + kBaudDiv) = div;
    mmio32(base_ + kCtrl) = kTxEnable | kRxEnable;
  }

  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                   std::uint32_t /*timeout_us*/) noexcept override {
    n_read = 0;
    while (n_read < buf.size() && (mmio32(base_ + kState) & kRxFull) != 0)
      buf[n_read++] = static_cast<std::uint8_t>(mmio32(base_ + kData) & 0xFFu);
    return n_read > 0 ? hal::Status::kOk : hal::Status::kTimeout;
  }

  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override {
    n_written = 0;
    if ((mmio32(base_ + kCtrl) & kTxEnable) == 0) return hal::Status::kNotReady;
    for (const std::uint8_t b : data) {
      while ((mmio32(base_ + kState) & kTxFull) != 0) {
      }
      mmio32(base_ + kData) = b;
      ++n_written;
    }
    return hal::Status::kOk;
  }

 private:
  static constexpr std::uintptr_t kData = 0x00, kState = 0x04, kCtrl = 0x08, kBaudDiv = 0x10;
  static constexpr std::uint32_t kTxFull = 1u << 0, kRxFull = 1u << 1;
  static constexpr std::uint32_t kTxEnable = 1u << 0, kRxEnable = 1u << 1;
  std::uintptr_t base_;
};

class Stm32Usart final : public hal::SerialPort {
 public:
  static constexpr std::uintptr_t kUsart2 = 0x40004400u;

  constexpr explicit Stm32Usart(std::uintptr_t base) noexcept : base_(base) {}

  // 8N1, oversampling by 16: BRR = f_pclk / baud (mantissa.fraction in one division).
  void init(std::uint32_t pclk_hz, std::uint32_t baud) noexcept {
    mmio32(base_ + kBrr) = (pclk_hz + baud / 2) / baud;
    mmio32(base_ + kCr1) = kUe | kTe | kRe;
  }

  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                   std::uint32_t /*timeout_us*/) noexcept override {
    n_read = 0;
    while (n_read < buf.size() && (mmio32(base_ + kSr) & kRxne) != 0)
      buf[n_read++] = static_cast<std::uint8_t>(mmio32(base_ + kDr) & 0xFFu);
    return n_read > 0 ? hal::Status::kOk : hal::Status::kTimeout;
  }

  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override {
    n_written = 0;
    if ((mmio32(base_ + kCr1) & (kUe | kTe)) != (kUe | kTe)) return hal::Status::kNotReady;
    for (const std::uint8_t b : data) {
      while ((mmio32(base_ + kSr) & kTxe) == 0) {
      }
      mmio32(base_ + kDr) = b;
      ++n_written;
    }
    while ((mmio32(base_ + kSr) & kTc) == 0) {  // last frame out before returning
    }
    return hal::Status::kOk;
  }

 private:
  static constexpr std::uintptr_t kSr = 0x00, kDr = 0x04, kBrr = 0x08, kCr1 = 0x0C;
  static constexpr std::uint32_t kRxne = 1u << 5, kTc = 1u << 6, kTxe = 1u << 7;
  static constexpr std::uint32_t kRe = 1u << 2, kTe = 1u << 3, kUe = 1u << 13;
  std::uintptr_t base_;
};

}  // namespace magvec::app
