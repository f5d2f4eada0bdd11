# fem3d — common tasks. `make run` and `make test` set everything up on a fresh machine.
PYTHON ?= python3
PIP_STAMP := .venv-stamp

.PHONY: install browser codegen check-generated build test lint run view bench clean

install: $(PIP_STAMP)  ## the package, its dev tools and CHOLMOD where the machine allows it
$(PIP_STAMP): pyproject.toml setup.py generated/c/*.c scripts/install_cholmod.sh
	$(PYTHON) -m pip install -q -e '.[dev]'
	@bash scripts/install_cholmod.sh --if-possible $(PYTHON)
	@touch $(PIP_STAMP)

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

run: install  ## the main job on the built-in bunny scene
	$(PYTHON) -m fem3d run bunny --out runs/bunny

view: install  ## the interactive viewer on the bunny: open http://127.0.0.1:8080
	$(PYTHON) -m fem3d view bunny

bench: install  ## benchmarks vs peers -> docs/benchmarks.md (pip install -e .[bench] for the peers)
	$(PYTHON) -m bench --sizes 1e3,1e4,1e5 --threads 1 --groups energy,gradient,hessian_elements,hessian_csr,step
	$(PYTHON) -m bench --sizes 1e3,1e4,1e5 --groups analyze,factor,solve
	$(PYTHON) -m bench.kernel_throughput
	$(PYTHON) -m bench.scenes
	$(PYTHON) -m bench.newton_step --mesh arma --refine 0,1 --modes direct,reuse
	$(PYTHON) -m bench.newton_step --mesh box --tets 1e5 --steps 1 --swing 4 --repeats 1

clean:
	rm -rf build *.egg-info fem3d/*.so $(PIP_STAMP) .pytest_cache
