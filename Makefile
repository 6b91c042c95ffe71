# `make demo` and `make test` do all the set-up on a fresh machine.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip

.PHONY: install demo test truth-suite gpu-check clean

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

test: install
	$(PY) -m pytest -q tests

# Known edits drawn at random (scripts/truth_suite.py): a fresh seed each time, printed;
# `make truth-suite SEED=N` redraws the cases of seed N.
SEED ?=
truth-suite: install
	$(PY) scripts/truth_suite.py $(if $(SEED),--seed $(SEED))

# First contact with a GPU (scripts/gpu_check.py): one table in under 10 minutes, written as JSON
# (GPU_CHECK_OUT). Without CUDA it says so in one line and fails. gsplat (the `gsplat` extra of
# setup.py) is installed here when it does not import; `make test` never installs it.
GPU_CHECK_OUT ?= outputs/gpu_check/gpu_check.json
gpu-check: install
	@$(PY) scripts/gpu_check.py --require-cuda
	@$(PY) -c "import gsplat" 2>/dev/null || $(PIP) install -q -e ".[gsplat]"
	$(PY) scripts/gpu_check.py --out $(GPU_CHECK_OUT)

clean:
	rm -rf $(VENV) outputs
