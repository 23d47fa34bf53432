# The two commands of the README: `make demo` and `make test`.
# Both set up a fresh machine first (system libraries, a virtual environment, the package).
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: setup demo test test-slow test-portable lint bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/mmpa demo --out runs/demo

# the suite on up to 4 processes (pytest-xdist), a test file per process (its module
# fixtures built once; the longest files first: tests/conftest.py, an order that
# --no-loadscope-reorder keeps: xdist would hand out the files with the most tests first):
# 2 on the 2-core CI machine; one thread per library in each (the processes already fill the cores: OpenMP's
# and OpenBLAS's threads would only compete)
TEST_ENV := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
test: setup
	$(VENV)/bin/ruff check .
	$(TEST_ENV) $(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile --no-loadscope-reorder

# the suite as another x86-64 CPU runs it: numpy's AVX512 kernels off, 1 and 2 threads per
# library, then as `make test` (issue 32: a verdict never rides on the last bits of a float)
test-portable: setup
	$(VENV)/bin/ruff check .
	bash scripts/test-portable.sh

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) .setup-stamp
