# Unit tests of the portable core (cmocka, gcc with ASan + UBSan).
#     make -C firmware -f tests/tests.mk test     (or `make test` through firmware/Makefile)
# Builds into firmware/build/tests/. Needs libcmocka-dev. Works standalone or included.
TESTS_FW := $(patsubst %/,%,$(dir $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))))
ifndef CORE_SRCS
include $(TESTS_FW)/sources.mk
endif

TEST_CC ?= gcc
TEST_DIR := $(TESTS_FW)/build/tests
TEST_CFLAGS := $(filter-out -O2,$(CORE_CFLAGS)) -O1 -g -fno-omit-frame-pointer \
	-fsanitize=address,undefined -fno-sanitize-recover=all
TEST_INCS := $(addprefix -I$(TESTS_FW)/,$(CORE_INCS) core/src tests)
# test_uart_cfg checks the STM32 target's USART register values (a header with no hardware access)
TEST_INCS += -I$(TESTS_FW)/targets/stm32f405
TEST_LIBS := -lcmocka

TEST_NAMES := test_vectors test_modbus test_fifo test_seq test_safety test_uart_cfg
TEST_BINS := $(addprefix $(TEST_DIR)/,$(TEST_NAMES))
TEST_CORE_OBJS := $(patsubst core/src/%.c,$(TEST_DIR)/core/%.o,$(CORE_SRCS))
TEST_HEADERS := $(wildcard $(TESTS_FW)/core/include/*.h $(TESTS_FW)/core/src/*.h $(TESTS_FW)/tests/*.h) \
	$(TESTS_FW)/targets/stm32f405/uart_cfg.h $(TESTS_FW)/targets/stm32f405/stm32f405.h

.PHONY: test test-build test-clean
.SECONDARY: $(TEST_CORE_OBJS) $(TEST_DIR)/test_hal.o

test: $(TEST_BINS)
	@set -e; for t in $(TEST_BINS); do echo "== $$t"; ASAN_OPTIONS=detect_leaks=1 \
		UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 $$t; done

test-build: $(TEST_BINS)

$(TEST_DIR)/core/%.o: $(TESTS_FW)/core/src/%.c $(TEST_HEADERS)
	@mkdir -p $(dir $@)
	$(TEST_CC) $(TEST_CFLAGS) $(TEST_INCS) -c $< -o $@

$(TEST_DIR)/test_hal.o: $(TESTS_FW)/tests/test_hal.c $(TEST_HEADERS)
	@mkdir -p $(dir $@)
	$(TEST_CC) $(TEST_CFLAGS) -Wno-conversion $(TEST_INCS) -c $< -o $@

$(TEST_DIR)/test_%: $(TESTS_FW)/tests/test_%.c $(TEST_DIR)/test_hal.o $(TEST_CORE_OBJS) $(TEST_HEADERS)
	@mkdir -p $(dir $@)
	$(TEST_CC) $(TEST_CFLAGS) -Wno-conversion $(TEST_INCS) $< $(TEST_DIR)/test_hal.o \
		$(TEST_CORE_OBJS) $(TEST_LIBS) -o $@

test-clean:
	rm -rf $(TEST_DIR)
