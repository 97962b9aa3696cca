// SysTick (the ARMv7-M core timer, SYST_CSR/RVR/CVR at 0xE000E010) as the sample clock of the
// bare-metal boards: a periodic interrupt that stands in for the devices' data-ready lines, and
// a microsecond time base for latency figures. The board defines SysTick_Handler and calls
// on_interrupt(); the vector is in toolchain/boards/cortex_m_startup.c.
#pragma once

#include <cstdint>

#include "magvec/app/mmio_uart.hpp"

namespace magvec::app {

class SysTickClock {
 public:
  // counts_per_us: counts of the selected clock per microsecond; cpu_clock selects the processor
  // clock (CLKSOURCE = 1), otherwise the board's reference clock. False when the period does not
  // fit the 24-bit reload register.
  bool start(std::uint32_t period_us, std::uint32_t counts_per_us, bool cpu_clock,
             void (*tick)()) noexcept {
    const std::uint64_t reload = static_cast<std::uint64_t>(period_us) * counts_per_us;
    if (tick == nullptr || reload < 2 || reload > (1u << 24)) return false;
    stop();
    tick_ = tick;
    period_us_ = period_us;
    counts_per_us_ = counts_per_us;
    reload_ = static_cast<std::uint32_t>(reload - 1);
    ticks_ = 0;
    mmio32(kRvr) = reload_;
    mmio32(kCvr) = 0;  // any write clears the counter: the first period is a whole one
    mmio32(kCsr) = (cpu_clock ? kClkSource : 0u) | kTickInt | kEnable;
    return true;
  }
  void stop() noexcept { mmio32(kCsr) = 0; }
  void on_interrupt() noexcept {
    ticks_ = ticks_ + 1;
    if (tick_ != nullptr) tick_();
  }
  // Microseconds since start(): whole periods from the interrupt count plus the part of the
  // current one from the down-counter (re-read when an interrupt came in between).
  std::uint64_t time_us() const noexcept {
    for (;;) {
      const std::uint32_t before = ticks_;
      const std::uint32_t cvr = mmio32(kCvr);
      if (ticks_ != before) continue;
      return static_cast<std::uint64_t>(before) * period_us_ + (reload_ - cvr) / counts_per_us_;
    }
  }

 private:
  static constexpr std::uintptr_t kCsr = 0xE000E010u;
  static constexpr std::uintptr_t kRvr = 0xE000E014u;
  static constexpr std::uintptr_t kCvr = 0xE000E018u;
  static constexpr std::uint32_t kEnable = 1u << 0;
  static constexpr std::uint32_t kTickInt = 1u << 1;
  static constexpr std::uint32_t kClkSource = 1u << 2;

  void (*tick_)() = nullptr;
  std::uint32_t period_us_{1};
  std::uint32_t counts_per_us_{1};
  std::uint32_t reload_{0};
  volatile std::uint32_t ticks_{0};
};

// Sleeps until an interrupt unless idle() is false. Interrupts are masked around the check, so a
// tick between the check and the WFI is not lost: WFI wakes on an interrupt pending under PRIMASK.
inline void wait_for_interrupt_unless_busy(bool (*idle)()) noexcept {
  asm volatile("cpsid i" ::: "memory");
  if (idle()) asm volatile("dsb\n\twfi" ::: "memory");
  asm volatile("cpsie i" ::: "memory");
}

}  // namespace magvec::app
