#!/usr/bin/env python
"""Bytes per Gaussian, write/read seconds and round-trip PSNR of each export format
(gs_regional/bench/export.py).

    python scripts/bench_export.py [--size 256] [--views 8] [--donut ../shared/data/donut/donut.ply]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.export import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
