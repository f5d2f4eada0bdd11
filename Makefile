# fem3d — common tasks. `make run` and `make test` set everything up on a fresh machine.
PYTHON ?= python3
PIP_STAMP := .venv-stamp
RUN_STAMP := .venv-run-stamp

.PHONY: install browser codegen check-generated build test lint run view bench clean

install: $(PIP_STAMP)  ## the package, its dev tools and CHOLMOD where the machine allows it
$(PIP_STAMP): pyproject.toml setup.py generated/c/*.c scripts/install_cholmod.sh
	@echo "make install: installing fem3d[dev] into $(PYTHON) and building its C kernels (pip, quiet: a few minutes on a fresh machine)"
	$(PYTHON) -m pip install -q -e '.[dev]'
	@bash scripts/install_cholmod.sh --if-possible $(PYTHON)
	@touch $(PIP_STAMP)

# The build requirements and runtime dependencies of pyproject.toml, one word each.
DEPS = $(PYTHON) -c "import tomllib; p = tomllib.load(open('pyproject.toml', 'rb')); \
	print(' '.join(p['build-system']['requires'] + p['project']['dependencies']))"

# pip's byte-compiling of every installed module is half of the dependencies' install time
# (11 of 21 s of CPU); Python compiles what a run imports on its first import instead, unless
# it may not write bytecode (PYTHONDONTWRITEBYTECODE): then pip's compile is kept.
NO_COMPILE = $(if $(PYTHONDONTWRITEBYTECODE),,--no-compile)

# Runtime only, in stages that each say what they do. fem3d itself is built without build
# isolation (no second download of setuptools into a throw-away environment) and alongside
# the dependencies' install: the C compile (four translation units, ~40 s of CPU that
# setup.py spreads over the cores) needs only setuptools, and the install (~25 s of CPU)
# fills the cores' gaps. Fresh clone and venv, pip's cache warm, 2 cores at load 0.4-2: 39-41 s
# to the bunny's outputs (docs/elements.md, "Build time").
$(RUN_STAMP): pyproject.toml setup.py generated/c/*.c scripts/install_cholmod.sh  ## runtime only
	@if [ -f $(PIP_STAMP) ]; then :; else \
	  echo "make run: [1/3] installing fem3d's dependencies into $(PYTHON) and, alongside, building its C kernels (pip, quiet: up to a minute on a fresh machine)"; \
	  $(PYTHON) -m pip install -q "setuptools>=68" wheel || exit 1; \
	  $(PYTHON) -m pip install -q --no-deps --no-build-isolation -e . & build=$$!; \
	  $(PYTHON) -m pip install -q $(NO_COMPILE) $$($(DEPS)) || { wait $$build; exit 1; }; \
	  wait $$build || { echo "make run: building fem3d's C kernels failed (above)" >&2; exit 1; }; \
	  echo "make run: [2/3] CHOLMOD, the fast sparse solver, where this machine allows it"; \
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

# One pytest worker per core (pytest-xdist), each taking whole files: a file's module-level
# fixtures and state stay in one process. Files are handed out in the order tests/conftest.py
# gives them (slow and browser files first), not xdist's own (most tests first). A worker that
# dies is not replaced: the run fails at once naming the test (pytest-xdist 3.8 can wait
# forever for a replaced worker under --dist loadfile, pytest-xdist#784).
# PYTEST_WORKERS= runs the suite in one process.
PYTEST_WORKERS ?= -n auto --dist loadfile --no-loadscope-reorder --max-worker-restart=0

# The announcement comes first, before anything is installed (hence the sub-make).
test:  ## the test suite (what CI runs)
	@echo "make test: sets up fem3d[dev] and CHOLMOD, and installs Debian's chromium (apt-get, only when /usr/bin/chromium is missing) for the browser test of the viewer (tests/app/test_viewer_browser.py), then runs pytest, one worker per core"
	@$(MAKE) --no-print-directory install browser PYTHON=$(PYTHON)
	$(PYTHON) -m pytest -q $(PYTEST_WORKERS)

run: $(RUN_STAMP)  ## the main job (runtime dependencies only, not the [dev] tools) on the built-in bunny scene
	@echo "make run: [3/3] simulating the bunny into runs/bunny (then energy.png and preview.gif)"
	$(PYTHON) -m fem3d run bunny --out runs/bunny

view: $(RUN_STAMP)  ## the interactive viewer on the bunny: open http://127.0.0.1:8080
	$(PYTHON) -m fem3d view bunny

bench: install  ## every figure of docs/benchmarks.md in one run (~35 min; pip install -e .[bench] for the peers)
	bash bench/all.sh PYTHON=$(PYTHON)

clean:
	rm -rf build *.egg-info fem3d/*.so $(PIP_STAMP) $(RUN_STAMP) .pytest_cache
