# Two entry points for a fresh machine: `make demo` (the main job) and `make test` (the suite).
# Both create .venv on first use and install the project with the pinned constraints.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev,ray,tensorboard,mlflow,sumo]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/demo.py

test: $(STAMP)
	$(PY) -m ruff check mapets_rl recipes examples benchmarks tests
	$(PY) -m ruff format --check mapets_rl recipes examples benchmarks tests
	$(PY) -m pytest tests

bench: $(STAMP)
	$(PY) benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) runs
