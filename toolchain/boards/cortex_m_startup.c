/* Reset and vector table for Cortex-M4F/M7 images (qemu mps2-an386/an500, STM32F4).
 * Order on reset (nothing before the FPU is enabled may use a float instruction):
 *   1. CPACR (0xE000ED88): full access to CP10/CP11 (the FPU), DSB/ISB;
 *   2. copy .data from its load address in flash, clear .bss;
 *   3. board hook magvec_board_early_init() (semihosting handles, clocks, UART);
 *   4. __libc_init_array() (C++ static constructors), main(), exit(main's value).
 * MAGVEC_IRQ_COUNT (set per board by CMake) sizes the external interrupt part of the table. */
#include <stdint.h>
#include <stdlib.h>

#ifndef MAGVEC_IRQ_COUNT
#error "MAGVEC_IRQ_COUNT must be defined for the board"
#endif

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern void __libc_init_array(void);
extern int main(void);

void magvec_board_early_init(void);
void magvec_board_fault(uint32_t ipsr);

/* Weak defaults: boards override them. */
__attribute__((weak)) void magvec_board_early_init(void) {}
__attribute__((weak)) void magvec_board_fault(uint32_t ipsr) {
  (void)ipsr;
  for (;;) {
  }
}

/* -nostartfiles drops crti/crtn: __libc_init_array still calls _init. */
void _init(void) {}
void _fini(void) {}

void Reset_Handler(void) __attribute__((noreturn));
void Default_Handler(void);
/* SysTick: the boards' sample clock when they define it (an unexpected tick otherwise faults). */
void SysTick_Handler(void) __attribute__((weak, alias("Default_Handler")));

void Reset_Handler(void) {
  volatile uint32_t* const cpacr = (volatile uint32_t*)0xE000ED88u;
  *cpacr |= (0xFu << 20); /* CP10, CP11: full access */
  __asm volatile("dsb\n\tisb" ::: "memory");

  uint32_t* src = &_sidata;
  for (uint32_t* dst = &_sdata; dst < &_edata;)
    *dst++ = *src++;
  for (uint32_t* dst = &_sbss; dst < &_ebss;)
    *dst++ = 0;

  magvec_board_early_init();
  __libc_init_array();
  exit(main());
}

void Default_Handler(void) {
  uint32_t ipsr;
  __asm volatile("mrs %0, ipsr" : "=r"(ipsr));
  magvec_board_fault(ipsr);
  for (;;) {
  }
}

typedef void (*Vector)(void);

/* Core exceptions and MAGVEC_IRQ_COUNT external interrupts, all but reset and SysTick to
 * Default_Handler. */
__attribute__((section(".isr_vector"), used)) const Vector g_vectors[16 + MAGVEC_IRQ_COUNT] = {
    [0] = (Vector)&_estack,
    [1] = Reset_Handler,
    [2 ... 14] = Default_Handler,
    [15] = SysTick_Handler,
    [16 ... 15 + MAGVEC_IRQ_COUNT] = Default_Handler,
};
