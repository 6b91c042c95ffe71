"""`make gpu-check` (scripts/gpu_check.py, gs_regional/bench/gpu_report.py) without a GPU: the one-line
refusal, the GPU checks as tests (tests/gpu/: skipped saying why; each outcome of a check read back
from pytest's report as its row, time limits, the budget), the table and JSON, and what of the
checks (gs_regional/bench/gpu_checks.py) runs on a CPU: the float16 / bfloat16 InstructPix2Pix path
on the tiny models, `dtype: auto`, the render comparison."""
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from tiny_models_fixture import one_thread, tiny_models  # noqa: F401

from gs_regional.bench import gpu_checks, gpu_report
from gs_regional.guidance.instructpix2pix import InstructPix2Pix
from gs_regional.utils.pretrained import Pretrained, resolve_dtype

pytestmark = pytest.mark.usefixtures("one_thread")
from trial_helpers import ROOT
SCRIPT = ROOT / "scripts" / "gpu_check.py"
PROMPT = "give him a mustache"


# --------------------------------------------------------------------------- without CUDA
@pytest.mark.parametrize("extra", [[], ["--require-cuda"]])
def test_without_cuda_says_so_in_one_line_and_fails(tmp_path, extra):
    out = tmp_path / "gpu_check.json"
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="")  # no CUDA device, even on a GPU machine
    done = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), *extra], capture_output=True, text=True,
                          env=env, timeout=120, cwd=str(tmp_path))
    assert done.returncode == 1, done.stdout + done.stderr
    assert done.stdout.splitlines() == [gpu_checks.NO_CUDA_LINE]
    assert gpu_checks.NO_CUDA_LINE == (
        "gpu-check: no CUDA device (torch.cuda.is_available() is False); nothing was checked")
    assert not out.exists() and not (tmp_path / "outputs").exists()  # nothing was run or written


def test_makefile_target():
    text = (ROOT / "Makefile").read_text()
    assert "\ngpu-check: install\n" in text and "scripts/gpu_check.py --require-cuda" in text
    assert "\ntruth-suite: install\n" in text  # the other targets stay
    assert gpu_report.GPU_TESTS == str(ROOT / "tests" / "gpu")  # the checks it runs are those tests
    test_recipe = re.search(r"\ntest: install[^\n]*\n(.*?)(\n\n|$)", text, re.S).group(1)
    assert "gsplat" not in test_recipe and "pytest" in test_recipe  # `make test` never installs gsplat


# --------------------------------------------------------------------------- the checks as tests
FAKE_CONFTEST = """
from gs_regional.bench.pytest_plugin import (  # noqa: F401
    check, gpu_ctx, priors, pytest_collection_modifyitems, pytest_configure,
)
import pytest


@pytest.fixture
def priors_check():
    def broken(ctx):
        raise RuntimeError("the priors did not build")
    return broken
"""

FAKE_CHECKS = """
import os
import time

import pytest

from gs_regional.bench.gpu_checks import CheckFailed, Skip

pytestmark = pytest.mark.cuda


def ok(ctx):
    return {"seconds_s": 1.5, "count": 3}


def raises(ctx):
    raise RuntimeError("what went wrong first\\nthe last line of the error")


def skips(ctx):
    raise Skip("not on this machine")


def fails(ctx):
    raise CheckFailed("exit code 1: the run's last line")


def out_of_tolerance(ctx):
    return {"diff": 0.5, "_fail": "diff 0.5 > 0.001"}


def sleeps(ctx):
    time.sleep(float(os.environ.get("FAKE_SLEEP_S", "120")))


@pytest.mark.limit_s(500)
def test_ok(check):
    check.run(lambda ctx: {**ok(ctx), "limit_s": check.limit_s})


def test_raises(check):
    check.run(raises)


def test_skips(check):
    check.run(skips)


def test_fails(check):
    check.run(fails)


def test_out_of_tolerance(check):
    check.run(out_of_tolerance)


@pytest.mark.limit_s(2)
def test_sleeps(check):
    check.run(sleeps)


def test_priors(check, priors_check):
    check.run(priors_check, session_key="priors")


def test_after_the_priors(check, priors):
    check.run(ok)


def test_dies(check):
    if os.environ.get("FAKE_DIE"):
        print("going down", flush=True)
        os._exit(7)
    check.run(ok)
"""


@pytest.fixture
def fake_tests(tmp_path):
    folder = tmp_path / "fake_gpu"
    folder.mkdir()
    (folder / "conftest.py").write_text(FAKE_CONFTEST)
    (folder / "test_fake_checks.py").write_text(textwrap.dedent(FAKE_CHECKS))
    return folder


def run_fake(folder, tmp_path, only=(), **env):
    """pytest on the fake checks as make gpu-check runs it (a smoke run: no CUDA needed); the rows."""
    logs = tmp_path / "logs"
    logs.mkdir(exist_ok=True)
    xml, log = str(logs / "pytest.xml"), str(logs / "pytest.log")
    environ = {**os.environ, "GPU_CHECK": "1", "GPU_CHECK_SMOKE_ON_CPU": "1", "GPU_CHECK_WORK": str(tmp_path),
               "GPU_CHECK_BUDGET": "1000", **env}
    rc = gpu_report.run_pytest(str(folder), xml, log, environ, only)
    return rc, gpu_report.summarise(xml, log, rc)


def test_each_outcome_of_a_check_is_its_row(fake_tests, tmp_path, capsys):
    """A check's results, a failure (its reason: the error's last line, the check's own words, the
    tolerance it missed, its time limit), a skip, a check whose priors did not build: one row each,
    read back from pytest's report."""
    rc, rows = run_fake(fake_tests, tmp_path)
    assert rc == 1
    by = {r["name"]: r for r in rows}
    assert [r["name"] for r in rows] == ["ok", "raises", "skips", "fails", "out_of_tolerance", "sleeps", "priors",
                                         "after_the_priors", "dies"]
    assert by["ok"]["status"] == "ok" and by["ok"]["results"] == {"seconds_s": 1.5, "count": 3, "limit_s": 500}
    assert by["raises"]["status"] == "failed"
    assert by["raises"]["reason"] == "RuntimeError: the last line of the error"
    log = Path(by["raises"]["log"]).read_text()
    assert "Traceback" in log and "what went wrong first" in log  # the whole error is in the log
    assert (by["skips"]["status"], by["skips"]["reason"]) == ("skipped", "not on this machine")
    assert (by["fails"]["status"], by["fails"]["reason"]) == ("failed", "exit code 1: the run's last line")
    assert by["out_of_tolerance"]["status"] == "failed" and by["out_of_tolerance"]["results"] == {"diff": 0.5}
    assert by["out_of_tolerance"]["reason"] == "diff 0.5 > 0.001"
    assert (by["sleeps"]["status"], by["sleeps"]["reason"]) == ("failed", "timed out after 2 s")
    assert by["sleeps"]["seconds"] < 30
    assert (by["priors"]["status"], by["priors"]["reason"]) == ("failed", "RuntimeError: the priors did not build")
    assert (by["after_the_priors"]["status"], by["after_the_priors"]["reason"]) == ("skipped", "needs 'priors', which failed")
    assert by["ok"]["seconds"] > 0 and by["skips"]["seconds"] == 0
    report = gpu_report.build_report(rows, {"gpus": []}, budget_s=1000, wall_s=12.0)
    assert report["counts"] == {"ok": 2, "failed": 5, "skipped": 2}


def test_the_budget_skips_the_rest_and_bounds_each_check(fake_tests, tmp_path):
    """A check's limit is its own or what is left of the budget, the smaller; once less than
    MIN_CHECK_S is left, the checks after it are skipped saying so."""
    budget = gpu_checks.MIN_CHECK_S + 1
    rc, rows = run_fake(fake_tests, tmp_path, only=("ok", "sleeps", "dies"), GPU_CHECK_BUDGET=str(budget),
                        FAKE_SLEEP_S="1.5")
    by = {r["name"]: r for r in rows}
    assert rc == 0 and [r["status"] for r in rows] == ["ok", "ok", "skipped"]
    assert by["ok"]["results"]["limit_s"] <= budget < 500
    assert by["dies"]["reason"].startswith(f"the {budget:.0f} s budget is spent (") and by["dies"]["reason"].endswith(" s used)")


def test_a_crash_of_the_test_run_is_one_failed_row(fake_tests, tmp_path):
    rc, rows = run_fake(fake_tests, tmp_path, only=("ok", "dies"), FAKE_DIE="1")
    assert rc == 7
    assert [(r["name"], r["status"]) for r in rows] == [("pytest", "failed")]
    assert rows[0]["reason"].startswith("pytest ended (exit code 7) without a report of its checks")


@pytest.mark.parametrize("smoke,reason", [("0", gpu_checks.NO_CUDA_REASON), ("1", gpu_checks.NOT_ASKED_REASON)])
def test_the_gpu_tests_skip_saying_why(tmp_path, smoke, reason):
    """tests/gpu/ in `make test`: without CUDA each check is skipped naming that; with a device (a
    smoke run stands in for one here) only make gpu-check or `pytest -m cuda` runs them."""
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="", GPU_CHECK_SMOKE_ON_CPU=smoke, GPU_CHECK_WORK=str(tmp_path))
    env.pop("GPU_CHECK", None)
    xml = tmp_path / "report.xml"
    done = subprocess.run([sys.executable, "-m", "pytest", str(ROOT / "tests" / "gpu"), "-p", "no:xdist", "-p",
                           "no:cacheprovider", "-q", "-o", "junit_family=xunit1", f"--junitxml={xml}"],
                          capture_output=True, text=True, env=env, timeout=300, cwd=str(ROOT))
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    rows = gpu_report.rows_from_junit(str(xml))
    assert [r["name"] for r in rows] == list(gpu_checks.CHECKS)
    assert {(r["status"], r["reason"]) for r in rows} == {("skipped", reason)}
    assert all(r["what"] == gpu_checks.CHECKS[r["name"]].what for r in rows)


# --------------------------------------------------------------------------- table and JSON
def fake_rows():
    return [
        {"name": "gsplat_vs_torch", "what": "w", "status": "ok", "seconds": 12.345, "log": "/x/logs/a.log",
         "results": {"fwd_rgb_max_abs": 2.5e-06, "bwd_max_rel_of": "means", "gaussians": 50000, "finite": True,
                     "trial": "/somewhere/runs/x"}, "reason": None},
        {"name": "ip2p_bf16", "what": "w", "status": "skipped", "seconds": 0.0, "results": {},
         "reason": "Tesla V100 does not support bfloat16"},
        {"name": "two_process", "what": "w", "status": "failed", "seconds": 3.0, "results": {"wall_s": 1234.5},
         "reason": "exit code 1: ValueError: a | b"},
    ]


def test_table_and_json_from_rows(tmp_path):
    env = {"gpu": "NVIDIA H100 80GB HBM3", "gpus": ["NVIDIA H100 80GB HBM3"] * 2, "torch": "2.13.0+cu128",
           "cuda": "12.8", "gsplat": "1.5.3"}
    report = gpu_report.build_report(fake_rows(), env, budget_s=570, wall_s=321.04, settings={"resolution": 512})
    assert report["counts"] == {"ok": 1, "failed": 1, "skipped": 1}
    path = gpu_report.write_report(report, str(tmp_path / "deep" / "gpu_check.json"))
    back = json.loads(Path(path).read_text())
    assert back == json.loads(json.dumps(report))
    assert back["gpu"] == "NVIDIA H100 80GB HBM3" and back["gsplat"] == "1.5.3" and back["schema"] == 1
    assert [r["name"] for r in back["rows"]] == ["gsplat_vs_torch", "ip2p_bf16", "two_process"]
    table = gpu_report.format_table(report).splitlines()
    assert table[0] == ("gpu-check on NVIDIA H100 80GB HBM3 (2 GPUs), torch 2.13.0+cu128 (CUDA 12.8), gsplat 1.5.3: "
                        "1 ok, 1 failed, 1 skipped in 321 s (budget 570 s)")
    assert table[2:4] == ["| check | status | s | results | reason |", "| --- | --- | --- | --- | --- |"]
    assert table[4] == ("| gsplat_vs_torch | ok | 12.3 | fwd_rgb_max_abs 2.50e-06, bwd_max_rel_of means, "
                        "gaussians 50,000, finite yes | - |")  # paths stay in the JSON
    assert table[5] == "| ip2p_bf16 | skipped | - | - | Tesla V100 does not support bfloat16 |"
    assert table[6] == "| two_process | failed | 3.0 | wall_s 1,234 | exit code 1: ValueError: a / b |"
    assert [gpu_report.format_value(v) for v in (None, 0.0, 0.5, 12.3456, 2e-4, 7)] == ["-", "0", "0.5", "12.3", "2.00e-04", "7"]
    assert gpu_checks.last_line("Traceback ...\n  File x\nKeyError: 'a'\n\n") == "KeyError: 'a'"


# --------------------------------------------------------------------------- the two-process check
def test_two_process_command_and_its_failure(tmp_path, monkeypatch):
    ctx = {"work": str(tmp_path)}
    cmd = gpu_checks.two_process_command(ctx)
    assert cmd[1].endswith("launch.py") and cmd[cmd.index("--config") + 1].endswith(os.path.join("configs", "demo.yaml"))
    assert "--train" in cmd and "trainer.devices=2" in cmd and cmd[cmd.index("--gpu") + 1] == "0,1"
    (tmp_path / "logs").mkdir()
    failing = [sys.executable, "-c", "import sys; print('starting 2 processes'); "
               "sys.exit('RuntimeError: the strategy ddp is not supported yet')"]
    monkeypatch.setattr(gpu_checks, "two_process_command", lambda ctx: failing)
    with pytest.raises(gpu_checks.CheckFailed) as e:
        gpu_checks.check_two_process(ctx)
    assert str(e.value) == "exit code 1: RuntimeError: the strategy ddp is not supported yet"


# --------------------------------------------------------------------------- renderers on the CPU
def test_gsplat_check_is_skipped_off_cuda():
    with pytest.raises(gpu_checks.Skip, match="CUDA"):
        gpu_checks.check_gsplat_vs_torch({"device": "cpu"})


def test_render_comparison_on_cpu(monkeypatch):
    """The comparison itself (torch-rasterizer against itself here): zero differences, gradients
    reached; a renderer that is off by 2e-3 fails the forward tolerance."""
    ctx = {"device": "cpu", "render_gaussians": 300, "resolution": 48}
    same = gpu_checks.render_comparison(ctx, other="torch-rasterizer")
    assert "_fail" not in same and same["gaussians"] == 300 and same["size"] == 48
    assert same["visible_torch"] > 0 and same["visible_other_only"] == 0
    for key in ("fwd_rgb_max_abs", "fwd_alpha_max_abs", "fwd_depth_max_rel", "bwd_means_max_abs", "bwd_sh_rest_max_abs",
                "bwd_means2d_max_abs", "bwd_max_rel"):
        assert same[key] == 0.0, key

    import gs_regional.registry as registry

    real_find = registry.find

    class OffBy:  # a renderer whose colours are 2e-3 too bright
        def __init__(self, *a, **kw):
            self.inner = real_find("torch-rasterizer")()

        def render(self, *a, **kw):
            out = self.inner.render(*a, **kw)
            return {**out, "rgb": out["rgb"] + 2e-3}

    monkeypatch.setattr(registry, "find", lambda name, *a, **kw: OffBy if name == "off-by" else real_find(name, *a, **kw))
    off = gpu_checks.render_comparison(ctx, other="off-by")
    assert off["_fail"].startswith("forward rgb 2.00e-03 > 0.001 at 2304 pixels")
    assert off["bwd_max_rel"] == 0.0  # a constant offset leaves the gradients as they were

    # One pixel off: a Gaussian at the alpha cut-off (as gsplat on a GPU: 1.26e-3 at one pixel of 512²)
    # passes; one pixel off by more than such a Gaussian can make fails.
    def one_pixel(by):
        class OnePixel(OffBy):
            def render(self, *a, **kw):
                out = self.inner.render(*a, **kw)
                rgb = out["rgb"].clone()
                rgb[10, 10, 0] += by
                return {**out, "rgb": rgb}
        return OnePixel

    ctx = {"device": "cpu", "render_gaussians": 300, "resolution": 100}  # 1e-4 of 100² pixels: one may differ
    for by, fails in ((1.26e-3, False), (5e-3, True)):
        monkeypatch.setattr(registry, "find", lambda name, *a, **kw: one_pixel(by) if name == "off-by" else real_find(name, *a, **kw))
        res = gpu_checks.render_comparison(ctx, other="off-by")
        assert res["fwd_pixels_over_tol"] == 1 and ("_fail" in res) == fails, (by, res.get("_fail"))


# --------------------------------------------------------------------------- fp16 / bf16 on the CPU
@pytest.fixture(scope="module")
def ip2p_fp32(tiny_models):
    return InstructPix2Pix({"pretrained": tiny_models["ip2p"], "device": "cpu", "dtype": "float32",
                            "num_inference_steps": 4})


def images(b=2, h=32, w=40, seed=0):
    return torch.rand(b, h, w, 3, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("dtype,torch_dtype", [("float16", torch.float16), ("bfloat16", torch.bfloat16),
                                                ("fp16", torch.float16), ("bf16", torch.bfloat16)])
def test_half_precision_guidance_runs_on_cpu(tiny_models, ip2p_fp32, dtype, torch_dtype):
    """An explicit float16 / bfloat16 is honoured on the CPU too (only `auto` picks float32 there):
    the modules hold that dtype, the outputs are float32 images in [0, 1], close to float32's."""
    g = InstructPix2Pix({"pretrained": tiny_models["ip2p"], "device": "cpu", "dtype": dtype, "num_inference_steps": 4})
    assert g.dtype == torch_dtype and g.device.type == "cpu"
    assert {g.unet.dtype, g.vae.dtype, g.text_encoder.dtype} == {torch_dtype}
    x = images()
    edited = g.edit(x, x, PROMPT, seed=[3, 4])
    ref = ip2p_fp32.edit(x, x, PROMPT, seed=[3, 4])
    assert edited.dtype == torch.float32 and edited.shape == x.shape and torch.isfinite(edited).all()
    assert 0 <= float(edited.min()) and float(edited.max()) <= 1
    assert (edited - ref).abs().max() < 0.1
    partial = g.edit(x, x, PROMPT, t_start=500, seed=[3, 4])
    assert partial.dtype == torch.float32 and torch.isfinite(partial).all()
    rel = g.relevance(x, PROMPT, timestep=500, seed=[1, 2])
    assert rel.dtype == torch.float32 and rel.shape == x.shape[:3] and torch.isfinite(rel).all()
    ref_rel = ip2p_fp32.relevance(x, PROMPT, timestep=500, seed=[1, 2])
    # The relevance map is a difference of two noise predictions: bfloat16's 8-bit mantissa makes it
    # coarse (here up to 0.25 of the map's maximum off float32's, correlation 0.96; float16: 0.02).
    assert torch.corrcoef(torch.stack([rel.flatten(), ref_rel.flatten()]))[0, 1] > 0.9
    assert (rel - ref_rel).abs().max() < (0.05 if torch_dtype == torch.float16 else 0.4)
    assert g.unet_evals == 4 * 3 * 2 + 2 * 3 * 2 + 2 * 2  # full edit 4 steps, partial 2 (t 501, 251), relevance


@pytest.mark.parametrize("dtype", ["float16", "bfloat16"])
def test_ip2p_check_on_cpu_with_tiny_models(tiny_models, dtype):
    """The IP2P check itself (what it runs at 512² on the GPU), on the CPU at 32²."""
    steps = 3
    ctx = {"device": "cpu", "priors": {"ip2p": tiny_models["ip2p"]}, "resolution": 32, "schedule": {"ddim_steps": steps}}
    res = gpu_checks.ip2p_step(ctx, dtype)
    assert "_fail" not in res
    assert res["dtype"] == dtype and res["out_dtype"] == "float32" and res["finite"] is True
    assert res["resolution"] == 32 and "peak_gib" not in res  # CUDA memory only on CUDA
    assert res["unet_evals"] == 3 * (1 + 3) + 3 * steps + 2  # warm-up and 3 timed 1-step edits, one of 3 steps, relevance
    for key in ("load_s", "edit_1_step_s", f"edit_{steps}_steps_s", "relevance_s"):
        assert res[key] > 0, key


def test_dtype_auto_resolution(tiny_models, monkeypatch):
    """`dtype: auto` (the guidance's default) is float32 on the CPU and float16 on CUDA; an explicit
    dtype wins on either. CUDA is mocked: Pretrained resolves, it does not move anything."""
    assert InstructPix2Pix.Config().dtype == "auto"
    folder = tiny_models["ip2p"]
    cpu = Pretrained("InstructPix2Pix", folder, device="auto", dtype="auto")
    if not torch.cuda.is_available():
        assert (cpu.device.type, cpu.dtype) == ("cpu", torch.float32)
    assert Pretrained("InstructPix2Pix", folder, device="cpu", dtype="auto").dtype == torch.float32
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for device in ("auto", "cuda", "cuda:1"):
        p = Pretrained("InstructPix2Pix", folder, device=device, dtype="auto")
        assert (p.device.type, p.dtype) == ("cuda", torch.float16), device
    assert Pretrained("InstructPix2Pix", folder, device="auto", dtype="bf16").dtype == torch.bfloat16
    assert Pretrained("InstructPix2Pix", folder, device="auto", dtype="float32").dtype == torch.float32
    assert resolve_dtype("auto", torch.device("cuda", 0)) == torch.float16
    with pytest.raises(ValueError, match="unknown dtype 'float8'"):
        Pretrained("InstructPix2Pix", folder, device="cpu", dtype="float8")


# --------------------------------------------------------------------------- the donut edit's timing
def test_the_donut_timing_turns_the_safe_stops_off_and_fails_if_the_edit_stopped(tmp_path, monkeypatch):
    """Random weights stop a real edit after localization: the check turns the safe
    stops off so that every stage is timed, and a run that stops anyway is a failure, not a timing."""
    import gs_regional.launch as launch
    from gs_regional.bench import pipeline as bench_pipeline

    donut = tmp_path / "donut.ply"
    donut.write_bytes(b"ply")  # only its presence is checked before the (faked) launch
    ctx = {"device": "cpu", "models": "tiny", "resolution": 64, "work": str(tmp_path), "donut": str(donut),
           "priors": {"ip2p": "ip2p", "depth_anything": "da"}, "schedule": dict(gpu_checks.CPU_SMOKE_SETTINGS["schedule"])}
    argv = gpu_checks.donut_argv(ctx)
    assert set(bench_pipeline.RANDOM_WEIGHTS_NO_STOPS) <= set(argv)

    def fake_launch(stopped):
        def main(argv, custom_dir=None):
            save = tmp_path / "runs" / "gpu-check-donut" / f"tiny@{stopped or 'ran'}" / "save"
            save.mkdir(parents=True)
            (save / "metrics.json").write_text(json.dumps({"stopped": stopped, "seconds": {"localize": 1.0, "refine_edit": 2.0},
                                                           "unet_evals": 10}))
            return 0
        return main

    monkeypatch.setattr(launch, "main", fake_launch("views disagree"))
    with pytest.raises(gpu_checks.CheckFailed, match="stopped early \\(views disagree\\)"):
        gpu_checks.check_donut_edit(ctx)
    monkeypatch.setattr(launch, "main", fake_launch(None))
    res = gpu_checks.check_donut_edit(ctx)
    assert res["refine_edit_s"] == 2.0 and res["unet_evals"] == 10


# --------------------------------------------------------------------------- the paper's budget
def test_the_paper_budget_runs_each_size_and_writes_the_breakdown(tmp_path, monkeypatch):
    """check_paper_budget runs pipeline.py once per size (the paper's budget on a GPU: no schedule
    options, so pipeline.py's real-size BUDGETS apply; the smoke schedule on the CPU) and writes
    every run's stages, start-up, UNet share and batch beside the table."""
    from gs_regional.bench import pipeline as bench_pipeline

    gpu = {**json.loads(json.dumps(gpu_checks.GPU_SETTINGS)), "smoke": False, "work": str(tmp_path), "models_dir": None}
    argv = gpu_checks.paper_budget_argv(gpu, 100_000)
    assert "--no-load" in argv and "--fp16" in argv and "--cycles" not in argv and "--iterations" not in argv
    assert argv[argv.index("--gaussians") + 1] == "100000" and argv[argv.index("--in2n-steps") + 1] == "0"
    assert gpu["paper_gaussians"] == [100_000, 1_000_000] and "paper_budget" in gpu_checks.CHECKS

    ctx = {**json.loads(json.dumps(gpu_checks.CPU_SMOKE_SETTINGS)), "smoke": True, "work": str(tmp_path), "models_dir": None}
    assert "--cycles" in gpu_checks.paper_budget_argv(ctx, 2_000)
    seen = []

    def fake_main(argv):
        n = int(argv[argv.index("--gaussians") + 1])
        seen.append(n)
        run = {"seconds": {"localize": 1.0, "refine_edit": 2.0}, "seconds_total": 3.0, "wall_seconds": 5.0,
               "startup_seconds": 2.0, "startup_parts": {"system": 1.3, "unstaged": 0.5, "process": 0.2}, "unet_evals": 12, "unet_seconds": 1.5, "unet_share": 0.3,
               "batch_size": {"64x64": 1}, "prior_wait_seconds": 0.0, "vae_encodes": 3, "vae_decodes": 1,
               "cuda_peak_bytes": None, "peak_rss_bytes": 2**30, "gaussians_after": n}
        return {"models": "tiny", "dtype": "float32", "device": {"device": "cpu"}, "scene": {"gaussians": n, "width": 64},
                "schedule": {"cycles": 1}, "runs": {"regional-edit": run}}

    monkeypatch.setattr(bench_pipeline, "main", fake_main)
    res = gpu_checks.check_paper_budget(ctx)
    assert seen == [2_000, 4_000]
    assert res["2k_wall_s"] == 5.0 and res["4k_unet_share"] == 0.3 and res["2k_batch"] == "1"
    assert res["2k_startup_parts"] == "system 1.3, unstaged 0.5, process 0.2"
    with open(res["breakdown"]) as f:
        breakdown = json.load(f)
    assert os.path.dirname(res["breakdown"]) == str(tmp_path)
    assert set(breakdown["runs"]) == {"2k", "4k"}
    r = breakdown["runs"]["4k"]
    assert r["stages_s"] == {"localize": 1.0, "refine_edit": 2.0} and r["startup_s"] == 2.0 and r["unet_s"] == 1.5
    assert r["startup_parts_s"] == {"system": 1.3, "unstaged": 0.5, "process": 0.2}
    assert r["batch_size"] == {"64x64": 1} and r["peak_rss_gib"] == 1.0

    def failing(argv):
        raise SystemExit("step failed (exit code 1); log x:\nRuntimeError: CUDA out of memory")

    monkeypatch.setattr(bench_pipeline, "main", failing)
    with pytest.raises(gpu_checks.CheckFailed, match="2,000 Gaussians: RuntimeError: CUDA out of memory"):
        gpu_checks.check_paper_budget(ctx)
