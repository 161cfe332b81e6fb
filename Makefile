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

# ruff and import-linter at the versions pinned in the `dev` extra; the import contracts
# (pyproject.toml) are checked on the distribution as installed, where the folders are rsra.*
LINT_STAMP := $(VENV)/.lint-installed
$(LINT_STAMP): pyproject.toml $(STAMP)
	$(PIP_INSTALL) -e '.[dev]'
	touch $(LINT_STAMP)

lint: $(LINT_STAMP)
	$(BIN)/ruff check daq estimator sim_bus config rsra tests bench
	rm -rf build/lint build/lib  # setuptools keeps stale modules in build/lib
	$(BIN)/pip install -q --no-deps --no-compile --target build/lint . 2>&1 | grep -v "^WARNING: Location" || true
	cd build/lint && PYTHONPATH=. ../../$(BIN)/lint-imports --no-cache ../../pyproject.toml

clean:
	rm -rf $(VENV) build *.egg-info
