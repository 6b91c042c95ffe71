"""scripts/pareto.py (gs_regional/bench/pareto.py) --quick runs end to end: pareto.json with one record per run
and the metrics of §1, and the chart. The quick mode is a check of the script, not a measurement."""
from trial_helpers import run_quick

from gs_regional.bench import pareto, sweeps


def test_pareto_quick_writes_records_and_chart(tmp_path):
    payload = run_quick(pareto, tmp_path, "pareto.json")
    records = payload["records"]
    assert payload["quick"] is True
    assert [(r["method"], r["label"]) for r in records] == [
        ("regional-edit", "1x10 m3"), ("regional-edit", "2x15 m4"), ("in2n", "40 steps"), ("plain-vote", "1x10 m3")]
    for r in records:
        assert r["edit"] == "add" and r["overrides"] and r["warnings"] == [], r["key"]
        assert 0 < r["edit_seconds"] <= r["wall_seconds"] and r["unet_evals"] > 0
        assert 5 < r["psnr_region_vs_true_edit"] < 60 and 5 < r["psnr_region_source_vs_true_edit"] < 60
        assert 20 < r["psnr_unedited"] <= 120  # 120 dB: psnr's floor for identical pixels
        assert r["gaussians_after"] == r["gaussians_before"] + r["gaussians_added"] - r["gaussians_pruned"]
        assert r["ply_bytes"] > 0 and r["source_ply_bytes"] > 0
    regional = [r for r in records if r["method"] != "in2n"]
    # the regional edit improves on doing nothing even at these budgets (by ~2.5-4 dB; deterministic
    # seeds, the 1 dB margin covers float differences between CPUs)
    for r in regional:
        assert r["psnr_region_vs_true_edit"] > r["psnr_region_source_vs_true_edit"] + 1.0, r["key"]
        assert 0.5 < r["mask_iou"] <= 1.0
    # a bigger budget costs more UNet evaluations
    assert records[1]["unet_evals"] > records[0]["unet_evals"]
    png = tmp_path / "pareto_add.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_pareto_front_keeps_only_undominated_points():
    pts = [(3.0, 10.0), (1.0, 5.0), (2.0, 4.0), (4.0, 9.0), (5.0, 12.0)]
    assert sweeps.pareto_front(pts) == [(1.0, 5.0), (3.0, 10.0), (5.0, 12.0)]
