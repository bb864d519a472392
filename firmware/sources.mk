# The one list of firmware sources and flags. Read by firmware/Makefile (CI, `make firmware`)
# and by firmware/pio_sources.py (PlatformIO's extra_script), so both builds are the same.
# Keep it to plain `NAME = words` assignments (the PlatformIO script parses them).

CORE_SRCS = core/src/crc.c core/src/rtu.c core/src/modbus.c core/src/regs.c core/src/fifo.c core/src/seq.c core/src/safety.c core/src/core.c
CORE_INCS = core/include
CORE_CFLAGS = -std=c11 -Wall -Wextra -Wshadow -Wconversion -Wno-sign-conversion -Werror -O2

# --- targets (owned by the targets engineer) ---------------------------------------------------
# STM32F405 image: Cortex-M4F, hard float, newlib-nano, own startup (no crt0), own linker script.
STM32_SRCS = targets/stm32f405/startup.c targets/stm32f405/clock.c targets/stm32f405/uart.c targets/stm32f405/leds.c targets/stm32f405/io.c targets/stm32f405/main.c
STM32_INCS = targets/stm32f405
STM32_CFLAGS = -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 -ffunction-sections -fdata-sections -ffreestanding -fno-common -g3
STM32_LDSCRIPT = targets/stm32f405/stm32f405rg.ld
STM32_LDFLAGS = -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 --specs=nano.specs -nostartfiles -Wl,--gc-sections -Wl,--print-memory-usage
STM32_LIBS = -lc -lgcc

# POSIX simulator: the same core as a host process behind a pty.
POSIX_SRCS = targets/posix/main.c targets/posix/sim_clock.c targets/posix/sidechan.c
POSIX_INCS = targets/posix
POSIX_CFLAGS = -D_XOPEN_SOURCE=700 -D_DEFAULT_SOURCE -g
POSIX_LDFLAGS =
POSIX_LIBS =
