"""The pytest side of the GPU checks (gpu_checks.py): the `cuda` and `limit_s` markers, the skip of
a check where CUDA is absent or that was not asked for, and the fixtures the tests of tests/gpu/
use (tests/gpu/conftest.py imports them): `check` runs one check function within its time limit
and the budget and records its results in the test's report (the `gpu_check_results` property of
pytest's --junitxml, which gpu_report.py reads back); `priors` hands the prior folders to the
checks that need them."""
from __future__ import annotations

import gc
import json
import os
import signal
import time
import traceback
from typing import Callable, Optional

import pytest

from gs_regional.bench import gpu_checks as checks

RESULTS_PROPERTY = "gpu_check_results"
_SESSION: dict = {}  # when the first check began; the priors' outcome


class CheckTimedOut(BaseException):
    """Raised in a check by its time limit (a BaseException: a check's own `except Exception` lets it through)."""


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "cuda: a GPU check (gs_regional/bench/gpu_checks.py): skipped without CUDA; "
                                       "make gpu-check (or pytest -m cuda) runs it")
    config.addinivalue_line("markers", "limit_s(seconds): the most a GPU check may run (default: gpu_checks.CHECKS)")


def skip_reason(config) -> Optional[str]:
    """Why the GPU checks do not run here: no CUDA device (unless a smoke run on the CPU), or not
    asked for (make gpu-check sets GPU_CHECK=1; `pytest -m cuda` asks too). None when they run."""
    import torch

    if not torch.cuda.is_available() and os.environ.get(checks.ENV_SMOKE) != "1":
        return checks.NO_CUDA_REASON
    if os.environ.get(checks.ENV_RUN) != "1" and "cuda" not in (config.getoption("markexpr", "") or ""):
        return checks.NOT_ASKED_REASON
    return None


def pytest_collection_modifyitems(config, items) -> None:
    marked = [item for item in items if item.get_closest_marker("cuda")]
    reason = skip_reason(config) if marked else None
    for item in marked if reason else ():
        item.add_marker(pytest.mark.skip(reason=reason))


class CheckRun:
    """One check of a test: `run(func)` calls func(ctx) and turns its outcome into the test's."""

    def __init__(self, name: str, ctx: dict, limit_s: float, record: Callable[[dict], None]):
        self.name, self.ctx, self.limit_s, self._record = name, ctx, limit_s, record

    def run(self, func: Callable[[dict], Optional[dict]], session_key: Optional[str] = None) -> dict:
        """func(ctx)'s results, recorded; Skip skips the test, CheckFailed, a `_fail` in the results,
        an error or the time limit fails it with the reason. `session_key` keeps the outcome for
        the checks that need this one (`priors`)."""
        try:
            results = dict(func(self.ctx) or {})
        except checks.Skip as e:
            _SESSION[session_key] = ("skipped", str(e))
            pytest.skip(str(e))
        except CheckTimedOut as e:
            _SESSION[session_key] = ("failed", str(e))
            pytest.fail(str(e), pytrace=False)
        except (Exception, SystemExit) as e:  # noqa: BLE001 - the row's reason; the whole error in the log
            traceback.print_exc()
            reason = str(e) if isinstance(e, checks.CheckFailed) else (
                f"{type(e).__name__}: {checks.last_line(str(e))}" if str(e).strip() else type(e).__name__)
            _SESSION[session_key] = ("failed", reason)
            pytest.fail(reason, pytrace=False)
        fail = results.pop("_fail", None)
        torch = _torch_if_cuda()
        if torch is not None and not fail:
            results.setdefault("cuda_peak_gib", checks._gib(torch.cuda.max_memory_allocated()))
        self._record(results)
        _SESSION[session_key] = ("failed", str(fail)) if fail else ("ok", results)
        if fail:
            pytest.fail(str(fail), pytrace=False)
        return results


def _torch_if_cuda():
    """torch when a CUDA context is up (its peak memory means something), else None."""
    import torch

    return torch if torch.cuda.is_available() and torch.cuda.is_initialized() else None


@pytest.fixture(scope="session")
def gpu_ctx() -> dict:
    """The checks' context (gpu_checks.context: settings, work folder, budget)."""
    return checks.context()


@pytest.fixture
def check(request, gpu_ctx, record_property):
    """A CheckRun for this test (test_<name>: the check `name`), limited to its own seconds or what
    is left of the budget, the smaller; skipped once less than MIN_CHECK_S is left."""
    name = request.node.name[len("test_"):] if request.node.name.startswith("test_") else request.node.name
    marker = request.node.get_closest_marker("limit_s")
    own = float(marker.args[0]) if marker else checks.CHECKS[name].limit_s if name in checks.CHECKS else 600.0
    start = _SESSION.setdefault("start", time.monotonic())
    used = time.monotonic() - start
    budget = gpu_ctx["budget_s"]
    if budget - used < checks.MIN_CHECK_S:
        pytest.skip(f"the {budget:.0f} s budget is spent ({used:.0f} s used)")
    limit = min(own, budget - used)
    torch = _torch_if_cuda()
    if torch is not None:
        torch.cuda.reset_peak_memory_stats()

    def timed_out(signum, frame):
        raise CheckTimedOut(f"timed out after {limit:.0f} s")

    previous = signal.signal(signal.SIGALRM, timed_out)
    signal.setitimer(signal.ITIMER_REAL, limit)
    try:
        yield CheckRun(name, gpu_ctx, limit, lambda r: record_property(RESULTS_PROPERTY, json.dumps(r, default=str)))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        gc.collect()
        if _torch_if_cuda() is not None:
            _torch_if_cuda().cuda.empty_cache()


@pytest.fixture
def priors_check() -> Callable[[dict], dict]:
    """The check that builds or finds the prior folders."""
    return checks.check_priors


@pytest.fixture
def priors(check, priors_check) -> dict:
    """The prior folders (test_priors' outcome, or found here when it did not run): a check that
    needs them is skipped when they did not build."""
    if "priors" not in _SESSION:
        try:
            _SESSION["priors"] = ("ok", priors_check(check.ctx))
        except checks.Skip as e:
            _SESSION["priors"] = ("skipped", str(e))
        except (Exception, SystemExit) as e:  # noqa: BLE001
            _SESSION["priors"] = ("failed", str(e))
    status, value = _SESSION["priors"]
    if status != "ok":
        pytest.skip(f"needs 'priors', which {status}")
    check.ctx["priors"] = {k: value[k] for k in ("ip2p", "depth_anything") if k in value}
    return check.ctx["priors"]
