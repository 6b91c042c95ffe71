#!/usr/bin/env python
"""Data-parallel editing: the diffusion stages of one edit on 1, 2, ... processes
(gs_regional/bench/parallel.py; --help says what it runs and writes).

    python scripts/bench_parallel.py --models tiny --out DIR                 # here: 1 and 2 CPU processes
    python scripts/bench_parallel.py --models real-size --out DIR            # a GPU machine: 1..N GPUs
    python scripts/bench_parallel.py --models real-size --out DIR --processes 1 2 4
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.parallel import cli  # noqa: E402

if __name__ == "__main__":
    sys.exit(cli())
