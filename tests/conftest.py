"""Test session set-up: never touch the network; locate the shared data."""
import os
import socket
from pathlib import Path

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

from trial_helpers import ROOT, launch  # noqa: E402 (after the environment above)

# ../shared/data beside the checkout; GS_REGIONAL_DATA points elsewhere (e.g. from a git worktree).
SHARED_DATA = Path(os.environ.get("GS_REGIONAL_DATA") or ROOT.parent / "shared" / "data")


class NetworkAccessError(RuntimeError):
    pass


_real_connect = socket.socket.connect


def _guarded_connect(self, address):
    host = address[0] if isinstance(address, tuple) else address
    if isinstance(host, str) and host not in ("127.0.0.1", "localhost", "::1") and not host.startswith("/"):
        raise NetworkAccessError(f"a test tried to reach the network: {address}")
    return _real_connect(self, address)


socket.socket.connect = _guarded_connect


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test with a clear reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p} (expected ../shared/data beside the checkout, or set GS_REGIONAL_DATA)")
    return p


@pytest.fixture
def shared():
    return shared_path


@pytest.fixture(scope="session")
def small_demo_run(tmp_path_factory):
    """One run of the small demo (tests/data/small_demo.yaml), shared by the tests that read its
    outputs or resume and compare against it: its trial dir."""
    return launch(tmp_path_factory.mktemp("small_demo"), "small-demo")
