# The two commands: `make demo` and `make test` (each creates .venv and installs if needed).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-all install fast bench clean

$(STAMP): pyproject.toml constraints.txt
	test -d $(VENV) || $(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/python experiments/demo.py

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m "slow or not slow"

# Optional CHOLMOD backend (needs Debian's libsuitesparse-dev and libopenblas0-pthread); the
# default install solves large scenes with AMG-PCG (pyamg) instead, .ci/run tests both.
fast: $(STAMP)
	$(BIN)/pip install --quiet -c constraints.txt -e ".[dev,fast]"

bench: $(STAMP)
	$(BIN)/python benchmarks/forward.py

clean:
	rm -rf $(VENV) runs *.egg-info
