# The STM32F4 image (build only): .isr_vector at 0x08000000 (flash), initial SP in SRAM, reset
# handler in flash. Exit 77 (skip) when the image has not been built.
if(NOT EXISTS "${ELF}")
  message("SKIP: ${ELF} not built (cmake --preset m4f && cmake --build --preset m4f)")
  cmake_language(EXIT 77)
endif()
find_program(OBJDUMP arm-none-eabi-objdump REQUIRED)
execute_process(COMMAND ${OBJDUMP} -h ${ELF} OUTPUT_VARIABLE headers COMMAND_ERROR_IS_FATAL ANY)
if(NOT headers MATCHES "\\.isr_vector +[0-9a-f]+ +08000000")
  message(FATAL_ERROR ".isr_vector not at 0x08000000:\n${headers}")
endif()
execute_process(COMMAND ${OBJDUMP} -s -j .isr_vector --start-address=0x08000000
                        --stop-address=0x08000008 ${ELF} OUTPUT_VARIABLE words)
# Little endian words: SP = 0x20xxxxxx (SRAM, top of the 128 KiB), PC = 0x08xxxxxx (flash).
set(h "[0-9a-f]")
if(NOT words MATCHES "8000000 ${h}${h}${h}${h}${h}${h}20 ${h}${h}${h}${h}${h}${h}08")
  message(FATAL_ERROR "unexpected initial SP/PC:\n${words}")
endif()
message("ok: STM32F4 vector table at 0x08000000, SP in SRAM, reset handler in flash")
