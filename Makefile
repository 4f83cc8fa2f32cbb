# imubench top-level Makefile. The two commands of README.md:
#   make demo   build what is needed and run a session against a device
#   make test   the static check (ruff, pyproject.toml) and the whole test suite (what CI runs through .ci/run)
# Both set up everything themselves on a fresh machine and are safe to run twice.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
BUILD  := build
HOST   := $(BUILD)/host

# Debian packages the host build and tests need (installed when missing, as root);
# chromium renders the HTML report in tests/results/test_report.py (headless, nothing downloaded);
# postgresql is the server tests/results/test_production_db.py starts in a temporary directory (the shared
# history database of a production line).
SYSTEM_PKGS := gcc make libc6-dev cppcheck chromium postgresql stm32flash

CC_HOST  ?= gcc
CFLAGS_HOST := -std=c11 -O2 -g -Wall -Wextra -Werror -Wshadow -Wstrict-prototypes \
               -Ifirmware/core -Ifirmware/drivers -Ifirmware/boards/sim/models -I$(HOST)/gen
# added to every C compile, host and ARM (setup.py, the wheel build, maps the source directory
# away with -ffile-prefix-map so that the wheel and the one built from the sdist are the same)
EXTRA_CFLAGS ?=
CFLAGS_HOST += $(EXTRA_CFLAGS)
# Portable firmware code (core, drivers) and the simulator's sensor models: compiled
# for the host into one static library that the C unit tests link against.
FW_PORTABLE_SRC := $(wildcard firmware/core/*.c firmware/drivers/*.c firmware/boards/sim/models/*.c)
FW_PORTABLE_OBJ := $(patsubst %.c,$(HOST)/obj/%.o,$(FW_PORTABLE_SRC))
C_TEST_SRC := $(wildcard tests/c/test_*.c)
C_TEST_BIN := $(patsubst tests/c/%.c,$(HOST)/tests/%,$(C_TEST_SRC)) $(HOST)/tests/vector_harness \
              $(HOST)/tests/param_check_harness

.PHONY: all test demo venv system-deps c-tests clean bench sim lint dist

all: c-tests

system-deps:
	@bash tools/ensure-system-deps.sh $(SYSTEM_PKGS)

$(VENV)/.stamp: pyproject.toml
	@$(PYTHON) -m venv $(VENV)
	@$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	@$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	@touch $@

venv: $(VENV)/.stamp

$(HOST)/obj/%.o: %.c $(wildcard firmware/core/*.h firmware/drivers/*.h firmware/boards/sim/models/*.h)
	@mkdir -p $(dir $@)
	$(CC_HOST) $(CFLAGS_HOST) -c $< -o $@

$(HOST)/libfw.a: $(FW_PORTABLE_OBJ)
	@mkdir -p $(dir $@)
	@rm -f $@
	ar rcs $@ $^

$(HOST)/tests/%: tests/c/%.c $(HOST)/libfw.a $(wildcard tests/c/*.h)
	@mkdir -p $(dir $@)
	$(CC_HOST) $(CFLAGS_HOST) -Itests/c $< $(HOST)/libfw.a -lm -o $@

c-tests: system-deps $(C_TEST_BIN)

# The virtual device: the firmware core and drivers built for Linux, with the sensor models
# behind the simulator board's SPI (firmware/boards/sim).
SIM_SRC := $(filter-out firmware/boards/sim/sim_lib.c,$(wildcard firmware/boards/sim/*.c))
SIM_BIN := $(HOST)/imubench-sim
$(SIM_BIN): $(SIM_SRC) $(HOST)/libfw.a $(wildcard firmware/boards/sim/*.h)
	$(CC_HOST) $(CFLAGS_HOST) -Ifirmware/boards/sim $(SIM_SRC) $(HOST)/libfw.a -lm -o $@

# The same models, physics, control channel and serial endpoint as a shared library for the
# ARM emulator (host/imubench/device/arm: the exact STM32 images under Unicorn), called
# through ctypes: one set of models for both targets (firmware/boards/sim/sim_lib.c).
SIM_LIB := $(HOST)/libimumodels.so
SIM_LIB_SRC := $(filter-out firmware/boards/sim/sim_main.c firmware/boards/sim/sim_loop.c,$(SIM_SRC)) firmware/boards/sim/sim_lib.c $(wildcard firmware/boards/sim/models/*.c) firmware/core/parts_gen.c
$(SIM_LIB): $(SIM_LIB_SRC) $(wildcard firmware/boards/sim/*.h firmware/boards/sim/models/*.h firmware/core/*.h)
	@mkdir -p $(dir $@)
	$(CC_HOST) $(CFLAGS_HOST) -fPIC -shared -Wl,--no-undefined -Ifirmware/boards/sim $(SIM_LIB_SRC) -lm -o $@

sim: system-deps $(SIM_BIN) $(SIM_LIB)

# Static analysis of every firmware C file (portable code, drivers, boards).
CPPCHECK_DIRS := $(wildcard firmware/core firmware/drivers firmware/boards/sim firmware/boards/stm32f1 firmware/boards/stm32f4 firmware/boards/common_arm)
lint: system-deps
	cppcheck --enable=warning,style,performance,portability --error-exitcode=1 --inline-suppr --quiet \
	    -Ifirmware/core -Ifirmware/drivers -Ifirmware/boards/sim -Ifirmware/boards/sim/models $(CPPCHECK_DIRS)

# Four workers on two cores (pytest-xdist): a lockstep session alternates between the host and
# its simulator, and many tests wait on a process they started, so fewer workers leave CPU idle
# (fresh clone, idle: 2 workers 13 min 46 s of pytest at 70 % of both cores, 3 workers 12 min 15 s
# at 86 %, on 2026-11-28 morning's suite; on the afternoon's, 3 workers 8 min 9 s and 8 min 14 s,
# 4 workers 6 min 47 s, in runs one after the other). A module's tests stay on one worker (--dist
# loadscope), so module- and session-scoped fixtures (a virtual bench, a database server) are set
# up once per worker; the workers take the modules heaviest first, in the order tests/conftest.py
# gives them (--no-loadscope-reorder; tests/module_seconds.json, rewritten from
# build/test-results.xml by tools/test-weights.py). The 30 slowest tests are listed at the end.
# The suite starts a few hundred Python processes; their bytecode is cached under build/pycache
# even where PYTHONDONTWRITEBYTECODE is set (each process would otherwise compile every module
# of imubench it imports again, about 0.1 s apiece).
PYTEST_WORKERS ?= 4
test: export PYTHONDONTWRITEBYTECODE :=
test: export PYTHONPYCACHEPREFIX := $(CURDIR)/build/pycache
test: system-deps venv c-tests sim firmware
	$(VENV)/bin/ruff check --no-cache host bench tests
	$(PY) -m pytest -n $(PYTEST_WORKERS) --dist loadscope --no-loadscope-reorder --durations=30 \
	    --junitxml=build/test-results.xml

demo: system-deps venv sim
	$(PY) -m imubench demo

clean:
	rm -rf $(BUILD)

# The release: the sdist, then the platform wheel built from it (setup.py compiles the virtual
# device, the models library and the STM32 images into the package), both into dist/.
# README.md, Install, says how to install either. It needs only what the build needs: the
# compilers (DIST_PKGS) and PyPA's `build` in a small environment of its own (DIST_VENV;
# `build` installs setuptools and wheel in its isolated build environment), not the test
# environment, Chromium or PostgreSQL. The wheel is reproducible (setup.py: SOURCE_DATE_EPOCH
# = the last commit's time): its SHA-256, printed here, is the one a build from the tree or
# pip's build from the sdist gives.
DIST_PKGS := gcc make libc6-dev gcc-arm-none-eabi libnewlib-arm-none-eabi git
DIST_VENV := $(BUILD)/dist-venv

$(DIST_VENV)/.stamp:
	@$(PYTHON) -m venv $(DIST_VENV)
	@$(DIST_VENV)/bin/python -m pip install -q --disable-pip-version-check "build>=1.0"
	@touch $@

dist: $(DIST_VENV)/.stamp
	@bash tools/ensure-system-deps.sh $(DIST_PKGS)
	@rm -rf dist
	$(DIST_VENV)/bin/python -m build --outdir dist .
	@ls -l dist
	@sha256sum dist/*.whl

include firmware/arm.mk

# Benchmarks print figures; they are not part of `make test`.
bench: venv
	@bash tools/ensure-system-deps.sh valgrind
	@$(PY) -m pip install -q --disable-pip-version-check -e '.[bench]'
	$(PY) bench/decode_throughput.py
	$(PY) bench/sim_stream.py
	$(PY) bench/core_instructions.py
	$(PY) bench/read_memory.py
	$(PY) bench/calib_solve.py
	@$(MAKE) --no-print-directory sim firmware
	$(PY) bench/multi_dut.py
	$(PY) bench/real_data.py
	$(PY) bench/arm_cycles.py
	$(PY) bench/session_time.py
	$(PY) bench/station_flood.py
	$(PY) bench/wheel_install.py
