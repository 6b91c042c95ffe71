"""The GPU checks' fixtures and markers (gs_regional/bench/pytest_plugin.py)."""
from gs_regional.bench.pytest_plugin import (  # noqa: F401
    check, gpu_ctx, priors, priors_check, pytest_collection_modifyitems, pytest_configure,
)
