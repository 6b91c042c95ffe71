"""scripts/compactness.py (gs_regional/bench/compactness.py) --quick runs end to end: compactness.json with one record per
run, the knee of each knob among the swept runs, and the chart. The quick mode is a check of the
script, not a measurement."""
from trial_helpers import run_quick

from gs_regional.bench import compactness


def test_compactness_quick_writes_records_knees_and_chart(tmp_path):
    payload = run_quick(compactness, tmp_path, "compactness.json")
    records = payload["records"]
    assert payload["quick"] is True
    assert [r["label"] for r in records] == [
        "default", "grad_threshold=0.0015", "budget=0", "prune_min_weight=5"]
    for r in records:
        assert r["edit"] == "add" and not r.get("error") and r["warnings"] == [], r["key"]
        assert r["net_added"] == r["gaussians_after"] - r["gaussians_before"] >= 0
        assert r["gaussians_added"] >= r["net_added"] and r["true_gaussians_added"] == 859
        assert 5 < r["psnr_region_vs_true_edit"] < 60 and 5 < r["psnr_region_source_vs_true_edit"] < 60
        assert 20 < r["psnr_unedited"] <= 120  # 120 dB: psnr's floor for identical pixels
    by = {r["label"]: r for r in records}
    default = by["default"]
    # densification adds Gaussians at the default; a budget of 0 or a high threshold stops it, so
    # only depth initialization adds any
    assert by["budget=0"]["gaussians_added"] < default["gaussians_added"]
    assert by["grad_threshold=0.0015"]["gaussians_added"] < default["gaussians_added"]
    # pruning runs after refinement: a higher threshold removes more of the same added Gaussians
    assert by["prune_min_weight=5"]["gaussians_added"] == default["gaussians_added"]
    assert by["prune_min_weight=5"]["gaussians_pruned"] > default["gaussians_pruned"]
    knees = payload["knees"]["add"]
    assert set(knees) == set(compactness.KNOBS)
    for knob, k in knees.items():
        swept = [r for r in records if r["knob"] in (knob, None)]
        assert k["knee_label"] in [r["label"] for r in swept], knob
        knee_run = by[k["knee_label"]]
        good = compactness.no_loss(swept)
        assert k["knee_net_added"] == knee_run["net_added"] == min(r["net_added"] for r in good)
        assert k["default_at_knee"] == (any(r is default for r in good) and
                                        default["net_added"] <= compactness.KNEE_SLACK * k["knee_net_added"])
    png = tmp_path / "compactness_add.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_knee_is_the_fewest_gaussians_within_the_margin_of_the_best():
    def rec(label, n, q):
        return {"label": label, "knob": "budget", "value": n, "net_added": n, "psnr_region_vs_true_edit": q}

    rows = [rec("a", 0, 17.0), rec("b", 100, 20.9), rec("c", 400, 21.1), rec("d", 800, 21.0)]
    assert compactness.knee(rows)["label"] == "b"  # 20.9 is within 0.25 dB of 21.1
    rows[1]["psnr_region_vs_true_edit"] = 20.8
    assert compactness.knee(rows)["label"] == "c"
    for r, ssim in zip(rows, (0.70, 0.80, 0.811, 0.813)):  # with SSIMs: structure may not be lost either
        r["ssim_region_vs_true_edit"] = ssim
    rows[1]["psnr_region_vs_true_edit"] = 20.9
    assert compactness.knee(rows)["label"] == "c"  # b keeps the PSNR but loses 0.013 SSIM
