#!/usr/bin/env python
"""Seconds and peak memory of the stages of a regional edit that grow with the number of Gaussians
(gs_regional/bench/scale.py; --help says what it measures).

    python scripts/bench_scale.py --sizes 100000 1000000 --out DIR
    python scripts/bench_scale.py --quick --out DIR          # 10k and 30k: a check, not a measurement
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.scale import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
