# `make demo` and `make test` do all the set-up on a fresh machine.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip

.PHONY: install demo test truth-suite clean

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

clean:
	rm -rf $(VENV) outputs
