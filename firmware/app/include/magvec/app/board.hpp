// Board layer of the firmware image: the few things the application needs from a board. Each
// board (boards/<name>/) implements these and its own main(), which calls app_main().
//   mps2:    qemu mps2-an386 (Cortex-M4F) / mps2-an500 (Cortex-M7): output and arguments over
//            ARM semihosting, the exit code goes back to qemu.
//   stm32f4: STM32F4 (build only): output on USART2 (polled), no arguments.
//   host:    a hosted executable built from the same sources (the reference run of the tests).
#pragma once

#include <cstddef>

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

// The application: runs the compiled-in scenario and reports. `args` is a space-separated
// option list (see app_main.cpp); returns the process exit code (0 = every check passed).
int app_main(const char* args) noexcept;

}  // namespace magvec::app
