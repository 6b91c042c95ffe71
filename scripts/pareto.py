#!/usr/bin/env python
"""Speed against accuracy: the regional edit at several budgets, in2n and the ablations, charted as
quality against cost (gs_regional/bench/pareto.py; --help says what it runs and writes).

    python scripts/pareto.py [--quick] [--out outputs/pareto] [--edits add recolor ...]
"""
import os
import sys

# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gs_regional.bench.pareto import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
