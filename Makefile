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
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --disable-pip-version-check -q torch==2.13.0
	$(PIP) install --disable-pip-version-check -q -e ".[train,dev,service,worker]" "torch==2.13.0"
	# LPIPS's calibrated layers, read as data: the package's own imports need torchvision.
	$(PIP) install --disable-pip-version-check -q --no-deps lpips==0.1.4
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q tests

deploy-test: $(STAMP)
	bash tests/deploy/run.sh

demo: $(STAMP)
	$(PY) -m core.cli demo

bench: $(STAMP)
	$(PY) benchmarks/rasterizer.py

clean:
	rm -rf build .pytest_cache
