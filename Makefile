# Two entry points: `make demo` opens the interactive viewer (http://127.0.0.1:8080), `make test` runs
# lint and the test suite (and the data-touching tests once more as on a machine without the shared folder).
# Both create .venv when it is missing. PYTHON picks the interpreter the venv is made from.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	# The pinned CPU build first, so nothing resolves a newer torch with CUDA packages.
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) -m apps.demo

lint: $(STAMP)
	$(PY) -m ruff check .

# The suite, then once more the tests that touch the shared data folder with PIE_SHARED_DATA pointing nowhere:
# a machine without ../shared (a user's fresh clone) must pass them too, skipping with the reason.
# torch runs on one OpenMP thread in the tests: on a 2-core machine where anything else runs, its spinning second
# thread made the Taichi- and torch-heavy tests 2x slower (7 % faster when the machine is otherwise idle).
test: lint
	OMP_NUM_THREADS=1 $(PY) -m pytest -q; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; rc=0; fi; test $$rc -eq 0 || exit $$rc
	OMP_NUM_THREADS=1 PIE_SHARED_DATA=$(CURDIR)/.no-shared-data $(PY) -m pytest -q -m data -p no:cacheprovider

bench: $(STAMP)
	$(PY) -m apps.bench --size paper --json out/bench.json

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
