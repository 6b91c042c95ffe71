"""Session-wide tiny random-weight priors (IP2P, Depth Anything, CLIP), built once and shared.

Import the fixtures into a test module with
    from tiny_models_fixture import tiny_models, one_thread  # noqa: F401
"""
import pytest
import torch

from gs_regional.testing.tiny_models import build_all

_CACHE = {}


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    """{"ip2p", "depth_anything", "clip"} -> folder. A module-level cache keeps it to one build per
    session even though each test module that imports this fixture registers its own copy."""
    if "paths" not in _CACHE:
        n = torch.get_num_threads()
        torch.set_num_threads(1)  # see one_thread
        try:
            _CACHE["paths"] = build_all(str(tmp_path_factory.mktemp("tiny_models")))
        finally:
            torch.set_num_threads(n)
    return _CACHE["paths"]


@pytest.fixture(scope="module", autouse=False)
def one_thread():
    """Tiny models run many very small ops; on a shared, oversubscribed CPU, intra-op threads spin
    and a 20-step edit goes from ~0.2 s to 10-25 s. One thread for the module, restored after."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
