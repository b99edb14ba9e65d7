# iotnav: two commands that work on a fresh machine (Python 3.11, pip, gcc).
#   make run    set up .venv and run the main job on the bundled default log
#   make test   set up .venv and run lint, format check, type check and the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/run

.PHONY: run test lint setup web bench clean

# The web map's browser library (Leaflet, pinned in package-lock.json) goes into the Python
# package: npm ci, then its dist files and LICENSE are copied (docstring of iotnav.service.web).
# Without npm the rest still installs and runs; the map page then says what is missing.
WEB_VENDOR := src/iotnav/service/web/static/vendor
LEAFLET := $(WEB_VENDOR)/leaflet/leaflet.js

web:
	@if [ -f $(LEAFLET) ] && [ $(LEAFLET) -nt package-lock.json ]; then :; \
	elif command -v npm >/dev/null 2>&1; then \
	  npm ci --ignore-scripts --no-audit --no-fund --loglevel=error && \
	  rm -rf $(WEB_VENDOR) && mkdir -p $(WEB_VENDOR)/leaflet && \
	  cp -R node_modules/leaflet/dist/leaflet.js node_modules/leaflet/dist/leaflet.css \
	    node_modules/leaflet/dist/images node_modules/leaflet/LICENSE $(WEB_VENDOR)/leaflet/; \
	else echo "warning: npm not found: the live map of iotnav serve needs it (apt-get install npm, then make setup)" >&2; fi

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP) web

run: setup
	$(BIN)/iotnav demo --out $(OUT)

lint: setup
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/mypy

# Tests on every core (pytest-xdist); a module's tests stay on one worker, so its module-scoped
# fixtures (simulated drives, ingested datasets) are built once. Compiled kernels are cached
# by iotnav itself (iotnav/__init__.py: one folder per source version), so a second run is warm.
# TEST_WORKERS=0 runs in one process. iotnav.warmup first compiles every engine's kernels once,
# shared over the cores, so the test workers do not each compile the same ones from an empty cache.
TEST_WORKERS ?= auto

test: lint
	$(BIN)/python -m iotnav.warmup --jobs $(TEST_WORKERS)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=40

bench: $(STAMP)
	$(BIN)/iotnav bench

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache node_modules $(WEB_VENDOR)
