"""scripts/bench_scale.py (gs_regional/bench/scale.py) runs end to end and writes the JSON other tools read."""
import json
import subprocess
import sys

from trial_helpers import ROOT
STAGES = ["ply_save", "ply_load", "render_512", "knn_pool", "localize", "selection_pieces", "append", "densify_prune",
          "checkpoint"]


def test_bench_scale_quick_writes_json_and_table(tmp_path):
    # --quick sizes (10k, 30k); small images and few views keep this a check, not a measurement
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_scale.py"), "--quick", "--out", str(tmp_path),
           "--render-size", "96", "--localize-views", "3", "--localize-size", "64"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((tmp_path / "bench_scale.json").read_text())
    assert list(results) == STAGES
    for stage, by_n in results.items():
        assert sorted(by_n, key=int) == ["10000", "30000"], stage
        for n, entry in by_n.items():
            assert entry["seconds"] > 0 and entry["cpu_seconds"] >= 0, (stage, n, entry)
            assert isinstance(entry["peak_bytes"], int) and entry["peak_bytes"] >= 0, (stage, n, entry)
    # the checkpoint's file: the scene's parameters (59 floats a row) and the moments of the 5% trained
    ckpt = results["checkpoint"]["30000"]["file_bytes"]
    assert 59 * 4 * 30_000 < ckpt < 1.3 * 59 * 4 * 30_000, ckpt
    # the table: one row per stage with a growth exponent between the two sizes
    assert "exp 10k→30k" in proc.stdout
    for stage in STAGES:
        row = next(line for line in proc.stdout.splitlines() if line.startswith(f"| {stage} |"))
        float(row.rstrip(" |").split("|")[-1])
