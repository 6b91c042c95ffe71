#!/usr/bin/env python
"""Speed and quality of `regional-edit` against the whole-scene `in2n` baseline on the synthetic
`add` edit (gs_regional/bench/edit.py; --help says what it runs).

    python scripts/bench_edit.py [--in2n-steps 300 600 1200] [--out outputs/bench_edit]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.edit import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
