# Quick start: `make demo` and `make test`. Both create .venv when missing.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench dist clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/kgadapt demo

# Two workers, a test file each at a time (module fixtures stay in one process): most tests wait on
# child processes, so two share the 2-core CI machine well (measured: 14 min against 19.5 in one process).
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile $(PYTEST_ARGS)

bench: $(STAMP)
	$(BIN)/kgadapt bench table1 --full

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache

# Offline install archives for x86_64 and aarch64 (docs/deploy.md); needs a package index once.
dist: $(STAMP)
	$(BIN)/python scripts/archive.py --out dist
