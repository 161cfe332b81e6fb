# Everything a user or CI needs goes through here; the venv is made on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# setuptools prints an information note on every editable install of a layout that is not
# src/ (ours maps config/ to rsra_config); silence that one note, nothing else
PIP_INSTALL := PYTHONWARNINGS="ignore:Editable installation" $(BIN)/pip install -q
# The editable install is setuptools' strict mode: a tree of links to the files
# (build/__editable__.rsra-*/rsra/daq/... -> daq/...) on one .pth path, for the venv's `rsra`
# run from any folder. (At the repository's top, rsra/daq -> ../daq and its siblings make the
# checkout itself the package: mypy, pyright and an IDE need no install.) A link tree holds the
# files that were there when it was made: a new, renamed or removed file in a package changes
# $(PKG_FILES) and the next `make` re-links.
PIP_EDITABLE := $(PIP_INSTALL) --config-settings editable_mode=strict -e
PKG_FILES := $(VENV)/.package-files
# the package files as a sorted list, rewritten only when it changes (its date is the rule's)
$(shell mkdir -p $(VENV) && find rsra daq estimator sim_bus config \( -name __pycache__ \
	-o -name openmct-dist \) -prune -o -type f ! -name '.*' ! -name '*~' ! -name '*.so' \
	! -name '*.pyc' -print | LC_ALL=C sort > $(PKG_FILES).new && \
	{ cmp -s $(PKG_FILES).new $(PKG_FILES) || mv $(PKG_FILES).new $(PKG_FILES); }; \
	rm -f $(PKG_FILES).new)

.PHONY: setup web demo test test-all bench lint metrics clean docs-img

# (setup.py and the C kernel too: an edited kernel is rebuilt into the venv by the next make;
# a file added to a package is linked by the next make)
$(STAMP): pyproject.toml setup.py daq/_hubkernel.c $(PKG_FILES)
	@echo "make: installing rsra into $(VENV) (once, about a minute): a virtual environment, then"
	@echo "      numpy, scipy, python-can, canopen, eclipse-zenoh, rich, matplotlib and the test and"
	@echo "      bench tools from PyPI (pyproject.toml); then the demo starts"
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(PIP_EDITABLE) '.[test,bench]'
	touch $(STAMP)

setup: $(STAMP)

# NASA Open MCT for `rsra web`, from the npm registry (package.json/package-lock.json pinned);
# its dist/ goes into the Python package (git-ignored; a wheel built after this includes it)
OPENMCT := daq/web/openmct-dist
$(OPENMCT)/openmct.js: package.json package-lock.json
	npm ci --no-audit --no-fund --ignore-scripts --loglevel=error
	rm -rf $(OPENMCT)
	mkdir -p $(OPENMCT)
	cp -R node_modules/openmct/dist/. $(OPENMCT)/
	cp node_modules/openmct/LICENSE.md $(OPENMCT)/
	find $(OPENMCT) -name '*.map' -delete
	rm -rf $(OPENMCT)/types

web: $(OPENMCT)/openmct.js

# docs/img/: the report's plots of a 60-s flight-rig run (rsra run --config flight --sim
# flight --speed max --record, replay, report --truth) and the browser view of a live ground
# test at 1600×1000 and 1280×800 (rsra run + rsra web on loopback, headless Chromium after
# two minutes); every process it starts is stopped at the end (about 4 minutes)
docs-img: $(STAMP) web
	$(BIN)/python -m tests.docs_img --out docs/img

demo: $(STAMP)
	$(BIN)/rsra demo

test: $(STAMP) web
	$(BIN)/python -m pytest -q

test-all: $(STAMP) web
	$(BIN)/python -m pytest -q -m "slow or soak or not (slow or soak)"

bench: $(STAMP)
	$(PIP_EDITABLE) '.[bench]'
	$(BIN)/python -m bench.run_all

# ruff, import-linter and mypy at the versions pinned in the `dev` extra; the import contracts
# (pyproject.toml) are checked on the distribution as installed, where the folders are rsra.*
LINT_STAMP := $(VENV)/.lint-installed
$(LINT_STAMP): pyproject.toml $(STAMP)
	$(PIP_EDITABLE) '.[dev]'
	touch $(LINT_STAMP)

# the complexity figures of docs/architecture.md's table: radon's mean cyclomatic complexity,
# the blocks at grade E/F and the classes over 300 lines (radon pinned in the `dev` extra)
metrics: $(LINT_STAMP)
	$(BIN)/python tests/test_metrics.py

lint: $(LINT_STAMP)
	$(BIN)/ruff check daq estimator sim_bus config rsra tests bench
	rm -rf build/lint build/lib build/bdist.*  # setuptools keeps stale modules in build/lib (and a cut-off build its bdist tree)
	$(BIN)/pip install -q --no-deps --no-compile --target build/lint . 2>&1 | grep -v "^WARNING: Location" || true
	cd build/lint && PYTHONPATH=. ../../$(BIN)/lint-imports --no-cache ../../pyproject.toml
	@# mypy ([tool.mypy]) reads rsra.* from the checkout itself: rsra/daq, rsra/estimator, … are
	@# links to the folders at the top (rsra/__init__.py), so its paths are rsra/daq/... = daq/...
	$(BIN)/mypy --config-file pyproject.toml -p rsra

clean:
	rm -rf $(VENV) build *.egg-info node_modules $(OPENMCT)
