"""Test session set-up: never touch the network; the shared data and the small demo's run as fixtures;
the order in which `make test` hands out the test files."""
import os
import socket

import pytest

# Before anything imports huggingface_hub / transformers / diffusers.
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["TRANSFORMERS_OFFLINE"] = "1"
os.environ["HF_DATASETS_OFFLINE"] = "1"
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
# Idle OpenMP threads sleep instead of spinning (see launch.py); set before torch is imported.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# With the tests spread over processes (`pytest -n`, as `make test` runs them), each gets its share
# of the cores for torch's threads instead of all of them; also set before torch is imported.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // _WORKERS)))

from trial_helpers import launch, shared_path  # noqa: E402 (after the environment above)


class NetworkAccessError(RuntimeError):
    pass


_real_connect = socket.socket.connect


def _guarded_connect(self, address):
    host = address[0] if isinstance(address, tuple) else address
    if isinstance(host, str) and host not in ("127.0.0.1", "localhost", "::1") and not host.startswith("/"):
        raise NetworkAccessError(f"a test tried to reach the network: {address}")
    return _real_connect(self, address)


socket.socket.connect = _guarded_connect


@pytest.fixture
def shared():
    return shared_path


@pytest.fixture(scope="session")
def small_demo_run(tmp_path_factory):
    """One run of the small demo (tests/data/small_demo.yaml), shared by the tests that read its
    outputs or resume and compare against it: its trial dir."""
    return launch(tmp_path_factory.mktemp("small_demo"), "small-demo")


# `make test` hands whole test files to its processes (pytest -n auto --dist loadfile), one at a
# time as a process runs out of work. xdist's default order (the files with the most tests first)
# leaves a file of one long test for the end, when the other process has nothing left to run: the
# longest files go first instead (by their --durations), and the many short ones even out the
# processes' ends; a file not named here runs after them.
LONGEST_FILES = (
    "test_regional_edit.py", "test_reliability.py", "test_float_stability.py", "test_parallel.py",
    "test_truth_suite.py", "test_studio.py", "test_bench_pipeline.py", "test_composite.py", "test_workflow_face.py",
    "test_bench_scale.py", "test_pareto.py", "test_formats.py", "test_gpu_check.py", "test_launch_console.py",
    "test_splat_truth.py", "test_reconstruct.py", "test_stability.py", "test_compactness.py",
    "test_device_and_batching.py", "test_viewer.py", "test_initialize_shape.py", "test_launch.py",
)


def pytest_configure(config):
    if hasattr(config.option, "loadscopereorder"):  # pytest-xdist: keep the order below
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(session, config, items):
    first = {name: rank for rank, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: first.get(item.path.name, len(first)))  # stable: the rest keep their order
