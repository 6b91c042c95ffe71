"""The GPU checks' table. `make gpu-check` (scripts/gpu_check.py: main) runs the tests of
tests/gpu/ with pytest (--junitxml) and reads the report back as one row per check: its status (ok,
failed, skipped), seconds, the results it recorded (gpu_checks.py: timings, differences, peak CUDA
memory) and the reason; with the machine (GPU names, the torch, CUDA, gsplat, diffusers,
transformers and lightning versions) it writes them as JSON and prints them as a markdown table.

    python scripts/gpu_check.py [--out outputs/gpu_check/gpu_check.json] [--budget 570] [--only CHECK ...]
    make gpu-check            # the same, after installing gsplat (the `gsplat` extra) if it is missing

Without CUDA it prints one line and exits 1; nothing is checked:
    gpu-check: no CUDA device (torch.cuda.is_available() is False); nothing was checked

pytest's output goes to the terminal and to logs/pytest.log beside the JSON (the whole error of a
failed check is there), its report to logs/pytest.xml, the runs to runs/. Exit status: 0 when
every check passed or was skipped, 1 without CUDA, 3 when a check failed.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from typing import Any, List, Mapping, Optional, Sequence

from gs_regional.bench import gpu_checks as checks
from gs_regional.bench.launching import ROOT
from gs_regional.bench.pytest_plugin import RESULTS_PROPERTY

SCHEMA_VERSION = 1
DEFAULT_OUT = os.path.join("outputs", "gpu_check", "gpu_check.json")
GPU_TESTS = os.path.join(ROOT, "tests", "gpu")
EXIT_NO_CUDA = 1
EXIT_FAILED = 3


# ------------------------------------------------------------------------------------ pytest
def run_pytest(tests: str, xml_path: str, log_path: str, env: Mapping[str, str], only: Sequence[str] = ()) -> int:
    """pytest on `tests` in a process of its own (its output to the terminal and to `log_path`, its
    report to `xml_path`); `only` names checks (test_<name>). Its exit code."""
    cmd = [sys.executable, "-m", "pytest", tests, "-p", "no:xdist", "-p", "no:cacheprovider", "-q", "-rfEs",
           "-o", "junit_family=xunit1", f"--junitxml={xml_path}"]
    if only:
        cmd += ["-k", " or ".join(f"test_{name}" for name in only)]
    for path in (xml_path, log_path):
        if os.path.exists(path):
            os.remove(path)
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                cwd=ROOT, env=dict(env), text=True, errors="replace")
        for line in proc.stdout:
            sys.stdout.write(line)
            log.write(line)
        return proc.wait()


def _message(text: Optional[str]) -> str:
    """A failure's or skip's reason as pytest's report gives it, without pytest's own prefixes."""
    text = (text or "").strip()
    for prefix in ("Failed: ", "Skipped: "):
        if text.startswith(prefix):
            text = text[len(prefix):]
    return text


def rows_from_junit(xml_path: str, log_path: Optional[str] = None) -> List[dict]:
    """One row per test case of pytest's JUnit XML: name (test_<name>: the check), what it checks,
    status, seconds, the results it recorded and the reason of a failure or a skip."""
    rows = []
    for case in ET.parse(xml_path).getroot().iter("testcase"):
        test = case.get("name", "")
        name = test[len("test_"):] if test.startswith("test_") else test
        props = {p.get("name"): p.get("value") for p in case.iter("property")}
        results = json.loads(props.get(RESULTS_PROPERTY) or "{}")
        status, reason = "ok", None
        skipped = case.find("skipped")
        if skipped is not None:
            status, reason = "skipped", _message(skipped.get("message"))
            # pytest names where the skip was raised: "path:line: reason"
            head, sep, tail = reason.partition(": ")
            if sep and ".py:" in head:
                reason = tail
        for tag in ("error", "failure"):
            element = case.find(tag)
            if element is not None:
                status, reason = "failed", _message(element.get("message"))
        seconds = 0.0 if status == "skipped" else float(case.get("time") or 0.0)
        what = checks.CHECKS[name].what if name in checks.CHECKS else ""
        row = {"name": name, "what": what, "status": status, "seconds": round(seconds, 2), "results": results,
               "reason": reason}
        if log_path:
            row["log"] = log_path
        rows.append(row)
    return rows


def summarise(xml_path: str, log_path: str, rc: int) -> List[dict]:
    """The rows of a pytest run; one failed row `pytest` when it ended without its report (a crash
    of the process, e.g. killed for memory) or collected nothing."""
    if os.path.isfile(xml_path):
        rows = rows_from_junit(xml_path, log_path)
        if rows or rc == 0:
            return rows
    tail = ""
    if os.path.isfile(log_path):
        with open(log_path, errors="replace") as f:
            tail = checks.last_line(f.read())
    return [{"name": "pytest", "what": "the GPU checks' test run", "status": "failed", "seconds": 0.0, "results": {},
             "reason": f"pytest ended (exit code {rc}) without a report of its checks: {tail or '(no output)'}; log {log_path}",
             "log": log_path}]


# ------------------------------------------------------------------------------------ report
def environment() -> dict:
    """GPU names and memory, versions of torch, CUDA, gsplat and the model libraries."""
    from importlib import metadata

    import torch

    def version(pkg: str) -> Optional[str]:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return None

    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    gpus = [torch.cuda.get_device_name(i) for i in range(n)]
    return {
        "gpu": gpus[0] if gpus else None, "gpus": gpus,
        "gpu_memory_gib": [checks._gib(torch.cuda.get_device_properties(i).total_memory) for i in range(n)],
        "torch": torch.__version__, "cuda": torch.version.cuda, "gsplat": version("gsplat"),
        "diffusers": version("diffusers"), "transformers": version("transformers"), "lightning": version("lightning"),
        "python": platform.python_version(), "host": platform.node(), "cpu_cores": os.cpu_count(),
    }


def build_report(rows: List[dict], env: dict, budget_s: float, wall_s: float, settings: Optional[dict] = None) -> dict:
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "skipped")}
    return {"schema": SCHEMA_VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **env,
            "budget_s": budget_s, "wall_s": round(wall_s, 1), "counts": counts, "settings": settings or {}, "rows": rows}


def format_value(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if v == 0:
            return "0"
        return f"{v:.2e}" if abs(v) < 1e-2 else f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return str(v)


def format_results(results: dict) -> str:
    # Paths (trials, reports, folders) are in the JSON; the table keeps the numbers.
    return ", ".join(f"{k} {format_value(v)}" for k, v in results.items()
                     if not (isinstance(v, str) and os.sep in v))


def format_table(report: dict) -> str:
    gpus = report.get("gpus") or []
    head = (f"gpu-check on {report.get('gpu') or 'no GPU'} ({len(gpus)} GPU{'s' if len(gpus) != 1 else ''}), "
            f"torch {report.get('torch')} (CUDA {report.get('cuda') or '-'}), gsplat {report.get('gsplat') or 'not installed'}: "
            f"{report['counts']['ok']} ok, {report['counts']['failed']} failed, {report['counts']['skipped']} skipped "
            f"in {report['wall_s']:.0f} s (budget {report['budget_s']:.0f} s)")
    lines = [head, "", "| check | status | s | results | reason |", "| --- | --- | --- | --- | --- |"]
    for r in report["rows"]:
        cells = [r["name"], r["status"], f"{r['seconds']:.1f}" if r["status"] != "skipped" else "-",
                 format_results(r["results"]) or "-", (r["reason"] or "").replace("|", "/") or "-"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(report: dict, path: str) -> str:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=2, default=str)
    os.replace(tmp, path)
    return path


# -------------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=DEFAULT_OUT, help=f"the JSON report (default {DEFAULT_OUT}); logs/ and runs/ beside it")
    ap.add_argument("--budget", type=float, default=checks.DEFAULT_BUDGET_S, help="seconds for all the checks together")
    ap.add_argument("--only", nargs="+", default=None, choices=list(checks.CHECKS), help="run only these checks")
    ap.add_argument("--models-dir", default=None, help="cache of the prior folders (default ~/.cache/gs_regional/priors)")
    ap.add_argument("--gaussians", type=int, default=None, help="bench_pipeline's scene size (default 1,000,000)")
    ap.add_argument("--require-cuda", action="store_true",
                    help="only say whether CUDA is there: the one line and exit 1 without it, exit 0 silently with it")
    ap.add_argument("--smoke-on-cpu", action="store_true", help=argparse.SUPPRESS)  # wiring check: tiny models, CPU
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import torch

    if not torch.cuda.is_available() and not args.smoke_on_cpu:
        print(checks.NO_CUDA_LINE, flush=True)
        return EXIT_NO_CUDA
    if args.require_cuda:
        return 0
    out = os.path.abspath(args.out)
    work = os.path.dirname(out)
    logs = os.path.join(work, "logs")
    os.makedirs(logs, exist_ok=True)
    env = dict(os.environ, HF_HUB_OFFLINE="1", TRANSFORMERS_OFFLINE="1", **{
        checks.ENV_RUN: "1", checks.ENV_WORK: work, checks.ENV_BUDGET: str(args.budget),
        checks.ENV_SMOKE: "1" if args.smoke_on_cpu else "0"})
    if args.models_dir:
        env[checks.ENV_MODELS_DIR] = os.path.abspath(args.models_dir)
    if args.gaussians:
        env[checks.ENV_GAUSSIANS] = str(args.gaussians)
    machine = environment()
    ctx = checks.context(env, gpus=len(machine["gpus"]))
    print(f"gpu-check: the tests of {os.path.relpath(GPU_TESTS, ROOT)} on "
          f"{machine['gpu'] or 'the CPU (smoke run: tiny models, the numbers mean nothing)'}, budget {args.budget:.0f} s; "
          f"log {os.path.join(logs, 'pytest.log')}", flush=True)
    t0 = time.monotonic()
    xml_path, log_path = os.path.join(logs, "pytest.xml"), os.path.join(logs, "pytest.log")
    rc = run_pytest(GPU_TESTS, xml_path, log_path, env, args.only or ())
    rows = summarise(xml_path, log_path, rc)
    report = build_report(rows, machine, args.budget, time.monotonic() - t0, ctx)
    write_report(report, out)
    print()
    print(format_table(report))
    print(f"\nwrote {out}")
    return EXIT_FAILED if report["counts"]["failed"] else 0
