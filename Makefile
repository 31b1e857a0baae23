# One command each: `make demo` tells the story on the shipped phantom (fit, diagnose the missing effect, refit, compare), `make test` runs the tests.
# Both set everything up on a fresh machine with Python 3.11 (venv, Python packages, and Debian's
# libusb-1.0-0 for open3d and chromium for the report's rendering test).
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
TEST_ARGS ?= -m "not slow"

.PHONY: setup demo test test-slow lint bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@# open3d imports only with Debian's libusb-1.0-0 present
	@ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || \
	  ( echo "installing libusb-1.0-0 (needed by open3d)"; \
	    $(SUDO) apt-get install -y -q libusb-1.0-0 || \
	    ( $(SUDO) apt-get update -q && $(SUDO) apt-get install -y -q libusb-1.0-0 ) )
	@# the report's picture test renders the HTML report in headless Chromium
	@command -v chromium >/dev/null 2>&1 || \
	  ( echo "installing chromium (renders the HTML report in the tests)"; \
	    $(SUDO) apt-get install -y -q chromium || \
	    ( $(SUDO) apt-get update -q && $(SUDO) apt-get install -y -q chromium ) )
	@[ -x $(BIN)/python ] || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev]"
	@touch $(STAMP)

demo: setup
	$(BIN)/breastmodel demo --out demo_out

test: setup
	$(BIN)/python -m pytest -q $(TEST_ARGS)

test-slow: setup
	$(BIN)/python -m pytest -q -m slow

lint: setup
	$(BIN)/ruff check .
	$(BIN)/python bench/house.py --json /dev/null
	$(BIN)/python -m pytest -q tests/test_layers.py tests/test_house.py

bench: setup
	$(BIN)/python bench/gravity.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache
