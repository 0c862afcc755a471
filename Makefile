# Every target sets itself up from a fresh clone: a local .venv, the project, its test extras.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
export NUMBA_CACHE_DIR ?= $(CURDIR)/.cache/numba

.PHONY: all setup run test bench clean browser

# Independent prerequisites at once: Chromium's install (network, dpkg) runs while pip installs the
# project and its kernels compile; what depends on what still runs in order.
MAKEFLAGS += -j2

all: test

# Compiled numba kernels, made again after an install or any change to analysis/: the first
# demo shot, job or `plenodust process` then loads them in a second instead of compiling.
KERNELS := .cache/numba/.warm
ANALYSIS_SOURCES := $(shell find analysis -name '*.py' 2>/dev/null)

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

$(KERNELS): $(STAMP) $(ANALYSIS_SOURCES)
	$(BIN)/plenodust warm-up
	@mkdir -p $(dir $@) && touch $@

setup: $(STAMP) $(KERNELS)

run: $(STAMP) $(KERNELS)
	$(BIN)/plenodust demo

# The dashboard test drives headless Chromium: install Debian's when it is missing and we
# are root; otherwise (or offline) that one test is skipped and says why.
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	  { if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
	        || echo "could not install chromium: the dashboard test will be skipped"; \
	    else echo "chromium missing (needs root and apt-get): the dashboard test will be skipped"; fi; }

# Three workers on two cores, each taking whole test files (their module fixtures are built once):
# the service tests mostly wait on subprocesses and sockets, and a third file's work fills those
# waits (the suite in 509 s against 574 s on two workers, same machine, kernels compiled).
test: $(STAMP) $(KERNELS) browser
	$(BIN)/python -m pytest -q -n 3 --dist loadfile

bench: $(STAMP) $(KERNELS)
	$(BIN)/python bench/run_all.py

clean:
	rm -rf $(VENV) .cache build *.egg-info
