# One-command entry points; each builds .venv/ itself on a fresh machine.
PYTHON ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: venv test test-fast lint demo bench clean

venv: $(STAMP)

$(STAMP): requirements.txt setup.py package.xml
	test -x $(VENV)/bin/python || $(PYTHON) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -r requirements.txt
	$(VENV)/bin/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

test: venv
	$(VENV)/bin/python -m pytest -q test

test-fast: venv  # everything but the slow tests (closed loops, colcon build)
	$(VENV)/bin/python -m pytest -q -m "not slow" test

lint: venv
	$(VENV)/bin/ruff check lompr_predictor test bench tools
	$(VENV)/bin/mypy

demo: venv
	$(VENV)/bin/lompr demo

bench: venv
	for script in bench/bench_*.py bench/soak_*.py; do $(VENV)/bin/python $$script || exit 1; done

clean:
	rm -rf $(VENV) build install log .pytest_cache
