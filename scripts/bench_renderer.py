#!/usr/bin/env python
"""Time and memory of a renderer on random scenes (gs_regional/bench/renderer.py).

    python scripts/bench_renderer.py                       # torch-rasterizer, CPU, full table
    python scripts/bench_renderer.py --counts 10000 --sizes 128 --threads 1
    python scripts/bench_renderer.py --device cuda --renderer gsplat-rasterizer
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.renderer import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
