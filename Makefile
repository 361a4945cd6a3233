# trimeter — the two commands a newcomer needs: `make demo` and `make test`.
# Everything else here is a step of those two. Set-up is idempotent (tools/setup.sh).
SHELL := /bin/bash
VENV   := .venv
PY     := $(VENV)/bin/python
FUZZ_SECONDS ?= 60

# Mitsuba's llvm_ad_* variants need LLVM >= 16; Debian's libllvm19 provides it (docs/platform-notes.md).
LIBLLVM := /usr/lib/x86_64-linux-gnu/libLLVM-19.so
ifneq ($(wildcard $(LIBLLVM)),)
export DRJIT_LIBLLVM_PATH ?= $(LIBLLVM)
endif
# One BLAS thread: the host code is single-core by design (benchmarks state "one core"), and on this
# 2-core machine idle OpenBLAS threads spin-wait under load, which stalled scipy's Delaunay for minutes.
export OPENBLAS_NUM_THREADS ?= 1

.PHONY: help setup native native-portable gen check-gen hardware lint typecheck firmware firmware-test fuzz pytest docs test demo bench gpu-check clean

help:
	@echo "make demo   - set up, start the twin with a virtual sample, run a press-button measurement, plot it"
	@echo "              (SENSOR=as7341: the twin reads like the AS7341 build, fitted band-aware)"
	@echo "              (SENSOR=c12880ma: the C12880MA build, spectra captured by the firmware)"
	@echo "make test   - set up, lint, build firmware (sim + stm32f405), run C unit tests, fuzz, and pytest"
	@echo "make bench  - the speed/accuracy benchmarks (map building, inversion)"
	@echo "make docs   - the documentation site, into build/docs (open build/docs/index.html)"

setup:
	@bash tools/setup.sh

# The compiled inversion kernel, loaded with ctypes (trimeter.inversion.native), rebuilt whenever one
# of its sources changes. Its boundary is invert.h; invert_abi.h and invert_h.py are generated from it.
# The library carries a hash of its sources: Python names a library older than them and runs numpy.
# Its sources are the host's own (NATIVE_DIR) and the inverse core it shares with the firmware
# (FIT_CORE_DIR: the table fit, tm_table_fit; one include path for both builds), hashed in that order.
NATIVE_DIR := host/trimeter/inversion/native
FIT_CORE_DIR := fit_core
NATIVE_LIB := $(NATIVE_DIR)/libtrimeter_invert.so
NATIVE_GEN := $(NATIVE_DIR)/invert_abi.h $(NATIVE_DIR)/invert_h.py
FIT_CORE_SOURCES = $(sort $(wildcard $(FIT_CORE_DIR)/*.c $(FIT_CORE_DIR)/*.h))
NATIVE_SOURCES = $(sort $(wildcard $(NATIVE_DIR)/*.c $(NATIVE_DIR)/*.h) $(NATIVE_DIR)/invert_abi.h) $(FIT_CORE_SOURCES)
# the kernel without library.c (the host's malloc'd entry points)
NATIVE_CORE := $(addprefix $(NATIVE_DIR)/,lookups.c newton.c simd.c pipeline.c) $(filter %.c,$(FIT_CORE_SOURCES))
$(NATIVE_GEN) &: $(NATIVE_DIR)/invert.h $(FIT_CORE_DIR)/table_fit.h tools/gen_native.py
	python3 -m tools.gen_native
# -O3 (the fit's loops inlined and unrolled further than -O2 does: faster, as `trimeter bench fit` shows) changes
# no result: without -ffast-math nothing is reassociated, and -std=c11 contracts nothing into FMAs.
$(NATIVE_LIB): $(NATIVE_SOURCES) $(NATIVE_GEN)
	$(CC) -O3 -std=c11 -Wall -Wextra -Werror -shared -fPIC -pthread -I$(FIT_CORE_DIR) \
	  -DTM_SOURCE_HASH=0x$$(cat $(NATIVE_SOURCES) | sha256sum | cut -c1-16)ULL \
	  -o $@ $(filter %.c,$(NATIVE_SOURCES)) -lm

native: $(NATIVE_LIB)

# The core also builds, warning-free, where it has no AVX2 path (any non-x86 host, e.g. an ARM
# single-board computer next to the instrument): compiled for the firmware's Cortex-M4 toolchain,
# which the firmware build needs anyway, as the stand-in for such a target.
native-portable: setup $(NATIVE_GEN)
	@mkdir -p build/invert-portable
	for src in $(NATIVE_CORE); do \
	  arm-none-eabi-gcc -O2 -std=c11 -Wall -Wextra -Werror -I$(FIT_CORE_DIR) -c -o build/invert-portable/$$(basename $$src .c).o $$src \
	  || exit 1; done

# Generated files (register map -> C header, Python module, Markdown; the docs' reference pages) are
# committed; check-gen fails when one of them is stale, so nobody edits a generated file by hand.
gen: setup
	$(PY) tools/gen_registers.py
	$(PY) -m tools.gen_native
	$(PY) -m tools.gen_docs

check-gen: setup
	$(PY) tools/gen_registers.py --check
	$(PY) -m tools.gen_hardware --check
	$(PY) -m tools.gen_native --check
	$(PY) -m tools.gen_docs --check

# The build documentation and printable parts (hardware/README.md): bom.md, wiring.md and the pictures
# in hardware/img (committed), STLs in build/hardware (not committed), all from hardware/*.toml.
hardware: setup
	$(PY) -m tools.gen_hardware --parts

# ruff's pycodestyle, pyflakes, bugbear and simplify rules (configured in pyproject.toml), after the type check
lint: setup typecheck
	$(VENV)/bin/ruff check host tools tests

# mypy over host/trimeter ([tool.mypy] in pyproject.toml); incremental through .mypy_cache
typecheck: setup
	$(VENV)/bin/mypy

firmware: setup
	$(MAKE) -C firmware all

firmware-test: setup
	$(MAKE) -C firmware test

fuzz: setup
	$(MAKE) -C firmware fuzz FUZZ_SECONDS=$(FUZZ_SECONDS)

# On both cores (pytest-xdist): one worker per core, each test file whole on one worker (its module fixtures made
# once, its tests in file order, as in a single process). PYTEST_WORKERS=0: the suite in this one process.
PYTEST_WORKERS ?= 2
pytest: setup firmware native
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile

# The documentation site (mkdocs.yml): --strict, so a broken link or anchor fails; nothing downloaded.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --quiet

# The checks before pytest are independent and each mostly on one core (the type check, the fuzzers): two at a
# time, each one's output printed whole when it ends. pytest then has both cores to itself.
test: setup check-gen
	$(MAKE) --no-print-directory -j2 --output-sync=target lint firmware firmware-test native-portable fuzz native
	$(MAKE) --no-print-directory pytest docs

SENSOR ?= spectrometer
demo: setup firmware native
	$(PY) -m trimeter demo --sensor $(SENSOR)

bench: setup firmware native
	$(PY) -m trimeter bench mapbuild
	$(PY) -m trimeter bench fit

# On a machine with an NVIDIA GPU: the map tracer's CUDA backend against LLVM on a few columns of each
# shipped recipe, then the inversion's tests (docs/maps-gpu-check.md). Elsewhere it prints SKIPPED, exit 0.
gpu-check: setup native
	$(PY) -m trimeter bench gpu-check

clean:
	$(MAKE) -C firmware clean || true
	rm -rf build out $(NATIVE_LIB)
