# Everything a user or CI needs goes through here; the venv is made on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# setuptools prints an information note on every editable install of a layout that is not
# src/ (ours maps config/ to rsra_config); silence that one note, nothing else
PIP_INSTALL := PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install -q

.PHONY: setup demo test test-all bench lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(PIP_INSTALL) -e '.[test,bench]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/rsra demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m "slow or soak or not (slow or soak)"

bench: $(STAMP)
	$(PIP_INSTALL) -e '.[bench]'
	$(BIN)/python -m bench.run_all

lint: $(STAMP)
	$(BIN)/pip install -q ruff
	$(BIN)/ruff check daq estimator sim_bus tests

clean:
	rm -rf $(VENV) build *.egg-info
