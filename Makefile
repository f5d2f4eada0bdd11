# fem3d — common tasks. `make run` and `make test` set everything up on a fresh machine.
PYTHON ?= python3
PIP_STAMP := .venv-stamp
RUN_STAMP := .venv-run-stamp

.PHONY: install browser codegen check-generated build test lint run view bench clean

install: $(PIP_STAMP)  ## the package, its dev tools and CHOLMOD where the machine allows it
$(PIP_STAMP): pyproject.toml setup.py generated/c/*.c scripts/install_cholmod.sh
	$(PYTHON) -m pip install -q -e '.[dev]'
	@bash scripts/install_cholmod.sh --if-possible $(PYTHON)
	@touch $(PIP_STAMP)

$(RUN_STAMP): pyproject.toml setup.py generated/c/*.c scripts/install_cholmod.sh  ## runtime only
	@if [ -f $(PIP_STAMP) ]; then :; else $(PYTHON) -m pip install -q -e .; \
	  bash scripts/install_cholmod.sh --if-possible $(PYTHON); fi
	@touch $(RUN_STAMP)

codegen:  ## regenerate generated/ from codegen/ and templates/, then rebuild the C extension
	$(PYTHON) -m codegen
	$(PYTHON) setup.py -q build_ext --inplace

check-generated:  ## fail with a diff when the committed generated/ is stale
	$(PYTHON) -m codegen --check

build:  ## rebuild the C extension in place after editing generated/c
	$(PYTHON) setup.py -q build_ext --inplace

lint:
	$(PYTHON) -m ruff check .

browser:  ## Debian chromium for the browser test (skipped with a reason if this fails)
	-@bash scripts/install_chromium.sh

test: install browser  ## the test suite (what CI runs)
	$(PYTHON) -m pytest -q

run: $(RUN_STAMP)  ## the main job (runtime dependencies only, not the [dev] tools) on the built-in bunny scene
	$(PYTHON) -m fem3d run bunny --out runs/bunny

view: $(RUN_STAMP)  ## the interactive viewer on the bunny: open http://127.0.0.1:8080
	$(PYTHON) -m fem3d view bunny

bench: install  ## every figure of docs/benchmarks.md in one run (~35 min; pip install -e .[bench] for the peers)
	bash bench/all.sh PYTHON=$(PYTHON)

clean:
	rm -rf build *.egg-info fem3d/*.so $(PIP_STAMP) $(RUN_STAMP) .pytest_cache
