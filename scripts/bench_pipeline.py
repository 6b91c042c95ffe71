#!/usr/bin/env python
"""The whole regional edit and the in2n baseline on one scene through the real code path, with
random-weight priors (gs_regional/bench/pipeline.py; --help says what it runs and writes).

    python scripts/bench_pipeline.py --models tiny|real-size --out DIR [options]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.pipeline import cli  # noqa: E402

if __name__ == "__main__":
    sys.exit(cli())
