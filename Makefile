# Set-up is idempotent: every target that runs code first makes sure the virtual
# environment (and, on Debian as root, the system packages) match pyproject.toml, with
# every extra (hardware backends, Dask; not gpu) at the exact versions of constraints.txt.
VENV ?= .venv
PYTHON ?= python3
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PYTEST_WORKERS ?= 2

.PHONY: setup demo test lint format bench lock clean

$(STAMP): pyproject.toml constraints.txt scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[all,dev]'
	touch $(STAMP)

# The decoder's numba kernels, compiled into their cache once per checkout (~2 CPU min; a
# second or so when cached, recompiled when a kernel's source changed): neither the first live
# capture of `phasecal serve` nor the tests' servers compile them while a pose waits.
# OpenCV's sample chessboard images (real data of the passive-target tests) are extracted
# into data/opencv-samples/ once.
setup: $(STAMP)
	$(PY) -m calibration.decode.kernel_warm
	bash scripts/fetch-opencv-samples.sh

demo: setup
	$(VENV)/bin/phasecal demo

# One BLAS/OpenMP thread per pytest worker: the workers already fill the cores, and
# oversubscribed BLAS threads made dense solves several times slower on 2 cores.
test: setup
	$(VENV)/bin/ruff check .
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
		$(PY) -m pytest -n $(PYTEST_WORKERS) tests

lint: setup
	$(VENV)/bin/ruff check .

format: setup
	$(VENV)/bin/ruff format .

bench: setup
	for b in benchmarks/*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

# Pin new dependencies into constraints.txt (then commit it); `bash scripts/lock.sh --upgrade`
# re-resolves every pin within pyproject.toml's ranges.
lock:
	bash scripts/lock.sh

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
