# `make demo` and `make test` do all the set-up on a fresh machine.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip

.PHONY: install browser demo test truth-suite gpu-check clean

$(VENV)/.installed: setup.py
	python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first and pinned: an unpinned torch pulls gigabytes of CUDA wheels.
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e ".[test]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(PY) launch.py --config configs/demo.yaml --train

# The browser tests (the viewer's page; our exports in the Spark web viewer) need Chromium:
# Debian's package, installed here when it is missing and apt-get may (root); otherwise this says
# so and those tests skip, naming it. Playwright drives it (the `test` extra of setup.py).
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing Debian's chromium for the browser tests"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get install -y -q chromium >/dev/null || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; } || \
	  echo "make test: apt-get could not install chromium: the browser tests will skip"; \
	else echo "make test: Chromium is missing and cannot be installed here (needs root and apt-get): the browser tests will skip"; fi

# On every core (pytest-xdist), a test file to a process: module fixtures are built once.
test: install browser
	$(PY) -m pytest -q -n auto --dist loadfile tests

# Known edits drawn at random (scripts/truth_suite.py, gs_regional/bench/truth/): a fresh seed
# each time, printed; `make truth-suite SEED=N` redraws the cases of seed N.
SEED ?=
truth-suite: install
	$(PY) scripts/truth_suite.py $(if $(SEED),--seed $(SEED))

# First contact with a GPU (scripts/gpu_check.py): the CUDA-marked tests of tests/gpu/ run with
# pytest and their results summarised in one table in under 10 minutes, written as JSON
# (GPU_CHECK_OUT). Without CUDA it says so in one line and fails. gsplat (the `gsplat` extra of
# setup.py) is installed here when it does not import; `make test` never installs it.
GPU_CHECK_OUT ?= outputs/gpu_check/gpu_check.json
gpu-check: install
	@$(PY) scripts/gpu_check.py --require-cuda
	@$(PY) -c "import gsplat" 2>/dev/null || $(PIP) install -q -e ".[gsplat]"
	$(PY) scripts/gpu_check.py --out $(GPU_CHECK_OUT)

clean:
	rm -rf $(VENV) outputs
