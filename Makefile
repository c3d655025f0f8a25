# All targets create .venv on first use and install the project from pyproject.toml.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo demo-headless sweep test bench fuzz clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[sim,console,sweep,test]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/swarmdrop run configs/paper_40.yaml --out runs/paper_40 --overwrite

demo-headless: $(STAMP)
	$(BIN)/swarmdrop simulate configs/paper_40.yaml --out runs/paper_40_headless --overwrite

sweep: $(STAMP)
	$(BIN)/swarmdrop sweep configs/paper_40_disturbed.yaml --seeds 100 --out runs/paper_40_disturbed_sweep --overwrite

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy companion sim_bridge swarmdrop/console
	@command -v chromium >/dev/null 2>&1 || test -x /usr/bin/chromium || \
		echo "note: no Chromium (/usr/bin/chromium): tests/test_console_browser.py will be SKIPPED (apt-get install -y chromium)"
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python -m compileall -q companion sim_bridge swarmdrop
	$(BIN)/python -m bench.run

fuzz: $(STAMP)
	$(BIN)/python -m sim_bridge.runs.fuzz --frames 1000000 --out runs/fuzz --json bench/results/fuzz.json

clean:
	rm -rf runs bench/results/*.json
