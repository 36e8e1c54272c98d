# Two commands for a new user:  make demo   and   make test
# PYTHON=/path/to/python3.12 overrides the interpreter search (tools/find-python).
VENV    ?= .venv
PY      := $(VENV)/bin/python
STAMP   := $(VENV)/.installed
WORKERS ?= 2

.PHONY: demo test test-quick bench clean venv

$(STAMP): pyproject.toml
	@base=$$(tools/find-python) || exit 1; \
	if [ ! -x "$(PY)" ]; then echo "creating $(VENV) with $$base"; "$$base" -m venv "$(VENV)" || exit 1; fi
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/cpas-bayes demo --out reports/demo

# One BLAS thread per test worker: WORKERS processes on as many cores, each with a spinning BLAS pool, would
# oversubscribe them (the package's own workers limit themselves the same way, core/executor.py).
ONE_THREAD := OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1

# --durations: every CI log names the slowest tests, where the suite's 30-minute budget goes
test: $(STAMP)
	$(ONE_THREAD) $(PY) -m pytest -n $(WORKERS) -q --durations=15

test-quick: $(STAMP)
	$(ONE_THREAD) $(PY) -m pytest -n $(WORKERS) -q -m "not slow"

bench: $(STAMP)
	$(PY) benchmarks/run.py

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
