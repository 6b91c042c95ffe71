"""The GPU checks (gs_regional/bench/gpu_checks.py), one test each: `make gpu-check` runs them and
summarises what each records into outputs/gpu_check/gpu_check.json; without CUDA, or outside
`make gpu-check` / `pytest -m cuda`, each is skipped saying why."""
import pytest

from gs_regional.bench import gpu_checks as checks

pytestmark = pytest.mark.cuda


def test_priors(check, priors_check):
    check.run(priors_check, session_key="priors")


def test_gsplat_vs_torch(check):
    check.run(checks.check_gsplat_vs_torch)


def test_ip2p_fp16(check, priors):
    check.run(checks.check_ip2p_fp16)


def test_ip2p_bf16(check, priors):
    check.run(checks.check_ip2p_bf16)


def test_bench_pipeline(check, priors):
    check.run(checks.check_bench_pipeline)


def test_paper_budget(check, priors):
    check.run(checks.check_paper_budget)


def test_donut_edit(check, priors):
    check.run(checks.check_donut_edit)


def test_two_process(check):
    if check.ctx["gpus"] < 2:
        pytest.skip(f"needs 2 GPUs; this machine has {check.ctx['gpus']}")
    check.run(checks.check_two_process)
