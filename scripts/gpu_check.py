#!/usr/bin/env python
"""First contact with a GPU: the GPU checks (the CUDA-marked tests of tests/gpu/) run with pytest
and summarised in one table, in under 10 minutes (gs_regional/bench/gpu_report.py; --help).

    python scripts/gpu_check.py [--out outputs/gpu_check/gpu_check.json] [--budget 570] [--only CHECK ...]
    make gpu-check            # the same, after installing gsplat (the `gsplat` extra) if it is missing
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.gpu_report import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
