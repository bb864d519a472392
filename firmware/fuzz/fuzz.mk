# libFuzzer harnesses for the portable core (clang, ASan + UBSan).
#     make -C firmware -f fuzz/fuzz.mk fuzz [FUZZ_SECONDS=20]
# FUZZ_SECONDS is the total, split evenly between the harnesses. Builds into build/fuzz/.
# Debian bookworm: clang-14 and libclang-rt-14-dev (libFuzzer + sanitizer runtimes), python3.
FUZZ_FW := $(patsubst %/,%,$(dir $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))))
ifndef CORE_SRCS
include $(FUZZ_FW)/sources.mk
endif

FUZZ_CC ?= clang
FUZZ_SECONDS ?= 20
FUZZ_DIR := $(FUZZ_FW)/build/fuzz
FUZZ_NAMES := fuzz_rtu fuzz_frame
FUZZ_BINS := $(addprefix $(FUZZ_DIR)/,$(FUZZ_NAMES))
FUZZ_CFLAGS := -std=c11 -g -O1 -fno-omit-frame-pointer \
	-fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
	$(addprefix -I$(FUZZ_FW)/,$(CORE_INCS))
FUZZ_CORE_CFLAGS := $(filter-out -O2 -Werror,$(CORE_CFLAGS)) -g -O1 -fno-omit-frame-pointer \
	-fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=all \
	$(addprefix -I$(FUZZ_FW)/,$(CORE_INCS))
FUZZ_CORE_OBJS := $(patsubst core/src/%.c,$(FUZZ_DIR)/core/%.o,$(CORE_SRCS))
FUZZ_HEADERS := $(wildcard $(FUZZ_FW)/core/include/*.h $(FUZZ_FW)/core/src/*.h $(FUZZ_FW)/fuzz/*.h)
EACH_SECONDS = $(shell expr $(FUZZ_SECONDS) / 2 \| 1)

.PHONY: fuzz fuzz-build fuzz-corpus fuzz-clean
.SECONDARY: $(FUZZ_CORE_OBJS)

fuzz: $(FUZZ_BINS) fuzz-corpus
	@set -e; for f in $(FUZZ_NAMES); do \
		kind=$${f#fuzz_}; mkdir -p $(FUZZ_DIR)/corpus/$$kind.live; \
		echo "== $$f ($(EACH_SECONDS) s)"; \
		$(FUZZ_DIR)/$$f -max_total_time=$(EACH_SECONDS) -max_len=4096 -timeout=10 \
			-print_final_stats=1 -artifact_prefix=$(FUZZ_DIR)/$$f- \
			$(FUZZ_DIR)/corpus/$$kind.live $(FUZZ_DIR)/corpus/$$kind; \
	done

fuzz-build: $(FUZZ_BINS)

fuzz-corpus: $(FUZZ_FW)/../protocol/vectors.toml $(FUZZ_FW)/fuzz/make_corpus.py
	@python3 $(FUZZ_FW)/fuzz/make_corpus.py $(FUZZ_DIR)/corpus

$(FUZZ_DIR)/core/%.o: $(FUZZ_FW)/core/src/%.c $(FUZZ_HEADERS)
	@mkdir -p $(dir $@)
	$(FUZZ_CC) $(FUZZ_CORE_CFLAGS) -c $< -o $@

$(FUZZ_DIR)/fuzz_%: $(FUZZ_FW)/fuzz/fuzz_%.c $(FUZZ_CORE_OBJS) $(FUZZ_HEADERS)
	@mkdir -p $(dir $@)
	$(FUZZ_CC) $(FUZZ_CFLAGS) $< $(FUZZ_CORE_OBJS) -o $@

fuzz-clean:
	rm -rf $(FUZZ_DIR)
