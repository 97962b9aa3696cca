// Board layer of the firmware image: the few things the application needs from a board. Each
// board (boards/<name>/) implements these and its own main(), which calls app_main().
//   mps2:    qemu mps2-an386 (Cortex-M4F) / mps2-an500 (Cortex-M7): output and arguments over
//            ARM semihosting, the exit code goes back to qemu.
//   stm32f4: STM32F4 (build only): output on USART2 (polled), no arguments.
//   host:    a hosted executable built from the same sources (the reference run of the tests).
#pragma once

#include <cstddef>
#include <cstdint>

#include "magvec/hal/serial_port.hpp"

namespace magvec::app {

// Output channel for the report lines (blocking, whole buffer).
void board_write(const char* s, std::size_t n) noexcept;
// Byte stream of the output records (RecordLineSink): uart = false -> the report channel
// (semihosting console / stdout), uart = true -> the board's UART (mps2: CMSDK UART0, i.e. qemu's
// first -serial; stm32f4: USART2, its only channel; host: stdout as well).
hal::SerialPort& board_record_port(bool uart) noexcept;
// Board name reported in the output.
const char* board_name() noexcept;

// Sample clock: a periodic interrupt standing in for the devices' data-ready lines (the ADC's
// DRDY, CAN receive). tick() runs in interrupt context every period_us. False when the board has
// none (host): the application then acquires from its main loop (polled).
bool board_start_sample_clock(std::uint32_t period_us, void (*tick)()) noexcept;
void board_stop_sample_clock() noexcept;
// Microseconds since the sample clock started (0 without one): latency figures only.
std::uint64_t board_time_us() noexcept;
// Sleeps until the next interrupt unless idle() returns false (checked with interrupts masked, so
// no wake-up is lost). Returns at once on a board without a sample clock.
void board_wait_for_interrupt(bool (*idle)()) noexcept;

// The application: runs the compiled-in scenario and reports. `args` is a space-separated
// option list (see app_main.cpp); returns the process exit code (0 = every check passed).
int app_main(const char* args) noexcept;

}  // namespace magvec::app
