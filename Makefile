# Fresh-machine entry points: `make demo` (commission a simulated sensor end to end) and `make test`.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
# Where pip takes torch from: empty = pip's configured index. From PyPI, Linux gets the multi-GB CUDA
# build; TORCH_INDEX=https://download.pytorch.org/whl/cpu takes the CPU build the tool needs.
TORCH_INDEX ?=

.PHONY: setup demo test bench chromium

$(BIN)/bubble: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --disable-pip-version-check $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) torch==2.13.0
	$(BIN)/pip install -q --disable-pip-version-check -e '.[dev]'
	touch $@

setup: $(BIN)/bubble

demo: setup
	$(BIN)/bubble commission --sim --out runs/demo

# The report test renders report.html in headless Chromium (Debian's package; root installs it).
chromium:
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
	  { [ "$$(id -u)" = 0 ] && apt-get update -qq && apt-get install -y -qq chromium >/dev/null; } || \
	  { echo "make test needs Chromium: sudo apt-get install chromium" >&2; exit 1; }

# Two worker processes (pytest-xdist): most tests wait on a simulated bench's real-time clock, so two
# share a 2-core machine; each test module runs in one of them, its shared fixtures made once
# (session 50, 2 cores: 596 s in one process; 403-420 s in two by test, 385 s by module).
TEST_WORKERS ?= 2

test: setup chromium
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadscope

bench: setup
	$(BIN)/python benchmarks/run_all.py
