# The one list of firmware sources and flags. Read by firmware/Makefile (CI, `make firmware`)
# and by firmware/pio_sources.py (PlatformIO's extra_script), so both builds are the same.
# Keep it to plain `NAME = words` assignments (the PlatformIO script parses them).

CORE_SRCS = core/src/crc.c core/src/rtu.c core/src/modbus.c core/src/regs.c core/src/fifo.c core/src/seq.c core/src/safety.c core/src/core.c
CORE_INCS = core/include
CORE_CFLAGS = -std=c11 -Wall -Wextra -Wshadow -Wconversion -Wno-sign-conversion -Werror -O2
