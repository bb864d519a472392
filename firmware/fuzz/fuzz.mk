# libFuzzer harnesses for the portable core (clang, ASan + UBSan).
#     make -C firmware fuzz [FUZZ_SECONDS=20]      both harnesses, FUZZ_SECONDS in total
#     make -C firmware fuzz-long [FUZZ_LONG_RUNS=5000000]   that many inputs per harness
#     make -C firmware fuzz-corpus                 regenerate the committed seed corpus
#     make -C firmware fuzz-coverage               line/branch coverage of the core by the corpora
# Seeds: fuzz/corpus/<harness>/ (committed; make_corpus.py from protocol/vectors.toml), plus a
# fresh generation from the current vectors in build/fuzz/corpus/. Units the fuzzer finds go
# to build/fuzz/corpus/<harness>.live/ (not committed). Builds into build/fuzz/.
# Debian bookworm: clang-14 and libclang-rt-14-dev (libFuzzer + sanitizer runtimes), python3.
FUZZ_FW := $(patsubst %/,%,$(dir $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))))
ifndef CORE_SRCS
include $(FUZZ_FW)/sources.mk
endif

FUZZ_CC ?= clang
FUZZ_SECONDS ?= 20
FUZZ_LONG_RUNS ?= 5000000
# Longest input. Every input costs in proportion to its length (a poll of the core scans every
# light source), and libFuzzer grows inputs up to this bound: 1 KiB holds 15 whole frames of
# fuzz_rtu or 4 FC 10 uploads of 120 registers in fuzz_frame: enough to load, start and play a
# sequence (corpus/*/fifo_fill).
FUZZ_MAX_LEN ?= 1024
FUZZ_DIR := $(FUZZ_FW)/build/fuzz
FUZZ_SEEDS := $(FUZZ_FW)/fuzz/corpus
FUZZ_NAMES := fuzz_rtu fuzz_frame
FUZZ_BINS := $(addprefix $(FUZZ_DIR)/,$(FUZZ_NAMES))
FUZZ_CFLAGS := -std=c11 -g -O2 -fno-omit-frame-pointer \
	-fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all \
	$(addprefix -I$(FUZZ_FW)/,$(CORE_INCS))
FUZZ_CORE_CFLAGS := $(filter-out -O2 -Werror,$(CORE_CFLAGS)) -g -O2 -fno-omit-frame-pointer \
	-fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=all \
	$(addprefix -I$(FUZZ_FW)/,$(CORE_INCS))
FUZZ_CORE_OBJS := $(patsubst core/src/%.c,$(FUZZ_DIR)/core/%.o,$(CORE_SRCS))
FUZZ_HEADERS := $(wildcard $(FUZZ_FW)/core/include/*.h $(FUZZ_FW)/core/src/*.h $(FUZZ_FW)/fuzz/*.h) $(FUZZ_FW)/fuzz/fuzz.mk
EACH_SECONDS = $(shell expr $(FUZZ_SECONDS) / 2 \| 1)

.PHONY: fuzz fuzz-long fuzz-build fuzz-corpus fuzz-seeds fuzz-coverage fuzz-clean
.SECONDARY: $(FUZZ_CORE_OBJS)

# $(call fuzz_run,LIBFUZZER_LIMIT): each harness from its live corpus and both seed sets.
define fuzz_run
	@set -e; for f in $(FUZZ_NAMES); do \
		kind=$${f#fuzz_}; mkdir -p $(FUZZ_DIR)/corpus/$$kind.live; \
		echo "== $$f ($(1))"; \
		$(FUZZ_DIR)/$$f $(1) -max_len=$(FUZZ_MAX_LEN) -timeout=10 \
			-print_final_stats=1 -artifact_prefix=$(FUZZ_DIR)/$$f- \
			$(FUZZ_DIR)/corpus/$$kind.live $(FUZZ_SEEDS)/$$kind $(FUZZ_DIR)/corpus/$$kind; \
	done
endef

fuzz: $(FUZZ_BINS) fuzz-seeds
	$(call fuzz_run,-max_total_time=$(EACH_SECONDS))

fuzz-long: $(FUZZ_BINS) fuzz-seeds
	$(call fuzz_run,-runs=$(FUZZ_LONG_RUNS))

fuzz-build: $(FUZZ_BINS)

# Seeds from the vectors as they are now (the committed set may lag a new vector).
fuzz-seeds: $(FUZZ_FW)/../protocol/vectors.toml $(FUZZ_FW)/fuzz/make_corpus.py
	@python3 $(FUZZ_FW)/fuzz/make_corpus.py --max-len $(FUZZ_MAX_LEN) $(FUZZ_DIR)/corpus

# The committed seed corpus: run after changing protocol/vectors.toml, then commit fuzz/corpus.
fuzz-corpus: $(FUZZ_FW)/../protocol/vectors.toml $(FUZZ_FW)/fuzz/make_corpus.py
	@python3 $(FUZZ_FW)/fuzz/make_corpus.py --max-len $(FUZZ_MAX_LEN) --clean $(FUZZ_SEEDS)

# safety.c scans every light source on every poll and every ds_core_next_deadline(): with
# comparison tracing that scan was 60 % of the fuzzers' time (perf record). Its comparisons are of
# device times and flags the core computed, never of input bytes, so tracing them gives libFuzzer
# no useful operands; crc.c's only comparison is its loop counter. Both keep their edge coverage
# and ASan/UBSan; only trace-cmp is dropped.
FUZZ_NO_TRACE_CMP := safety crc

$(FUZZ_DIR)/core/%.o: $(FUZZ_FW)/core/src/%.c $(FUZZ_HEADERS)
	@mkdir -p $(dir $@)
	$(FUZZ_CC) $(FUZZ_CORE_CFLAGS) $(if $(filter $*,$(FUZZ_NO_TRACE_CMP)),-fno-sanitize-coverage=trace-cmp) -c $< -o $@

$(FUZZ_DIR)/fuzz_%: $(FUZZ_FW)/fuzz/fuzz_%.c $(FUZZ_CORE_OBJS) $(FUZZ_HEADERS)
	@mkdir -p $(dir $@)
	$(FUZZ_CC) $(FUZZ_CFLAGS) $< $(FUZZ_CORE_OBJS) -o $@

# Source coverage of the core by everything in the corpora (seeds + what the fuzzers found):
# the harnesses rebuilt with clang's source-based coverage, each corpus replayed once (-runs=0).
FUZZ_COV_DIR := $(FUZZ_DIR)/cov
FUZZ_LLVM_PROFDATA ?= llvm-profdata
FUZZ_LLVM_COV ?= llvm-cov
fuzz-coverage: fuzz-seeds
	@mkdir -p $(FUZZ_COV_DIR)
	@set -e; for f in $(FUZZ_NAMES); do \
		kind=$${f#fuzz_}; mkdir -p $(FUZZ_DIR)/corpus/$$kind.live; \
		$(FUZZ_CC) -std=c11 -O1 -g -fsanitize=fuzzer -fprofile-instr-generate -fcoverage-mapping \
			$(addprefix -I$(FUZZ_FW)/,$(CORE_INCS)) $(FUZZ_FW)/fuzz/$$f.c \
			$(addprefix $(FUZZ_FW)/,$(CORE_SRCS)) -o $(FUZZ_COV_DIR)/$$f; \
		LLVM_PROFILE_FILE=$(FUZZ_COV_DIR)/$$f.profraw $(FUZZ_COV_DIR)/$$f -runs=0 \
			-max_len=$(FUZZ_MAX_LEN) $(FUZZ_DIR)/corpus/$$kind.live $(FUZZ_SEEDS)/$$kind \
			$(FUZZ_DIR)/corpus/$$kind > $(FUZZ_COV_DIR)/$$f.log 2>&1; \
		$(FUZZ_LLVM_PROFDATA) merge -sparse $(FUZZ_COV_DIR)/$$f.profraw -o $(FUZZ_COV_DIR)/$$f.profdata; \
		echo "== $$f: corpus $$(ls $(FUZZ_DIR)/corpus/$$kind.live | wc -l) found + seeds"; \
		$(FUZZ_LLVM_COV) report $(FUZZ_COV_DIR)/$$f -instr-profile=$(FUZZ_COV_DIR)/$$f.profdata \
			$(addprefix $(FUZZ_FW)/,$(CORE_SRCS)); \
	done

fuzz-clean:
	rm -rf $(FUZZ_DIR)
