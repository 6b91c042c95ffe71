"""scripts/stability.py (gs_regional/bench/stability.py) --quick runs end to end: stability.json with the records,
the break table and the charts; and the safe path of an instruction about nothing (the views
disagree about the region: the run warns and writes the source unchanged)."""
from pathlib import Path

import numpy as np
from trial_helpers import ply_arrays, run_quick

from gs_regional.bench import stability
from gs_regional.sim.scene import make_edit


def test_stability_quick_writes_records_table_and_charts(tmp_path):
    payload = run_quick(stability, tmp_path, "stability.json")
    records = {r["key"]: r for r in payload["records"]}
    assert sorted(records) == sorted([
        "add/regional-edit/default", "add/in2n/default", "add/regional-edit/leakage=0",
        "add/regional-edit/leakage=1.5", "empty/regional-edit/default"])
    for key, r in records.items():
        assert 0 < r["edit_seconds"] <= r["wall_seconds"], key
        assert r["psnr_unedited"] is None or 20 < r["psnr_unedited"] <= 120, key
        if r["edit"] == "add" and key != "add/regional-edit/leakage=1.5":
            assert 5 < r["psnr_region_vs_true_edit"] < 60 and r["warnings"] == [], key
    # more leakage selects more of what should not change (the body under the head)
    assert records["add/regional-edit/leakage=1.5"]["mask_iou"] < records["add/regional-edit/leakage=0"]["mask_iou"]
    # the table: in2n has no relevance, so leakage does not affect it
    assert payload["breaks"]["leakage"]["in2n"].startswith("not affected")
    # At leakage 1.5 the body lights up more than the head: the masks select the body, the first
    # edit lies mostly outside the selection, and the run stops safely (edit coverage below
    # localization.min_edit_coverage): the source is written unchanged, with one warning.
    strong = records["add/regional-edit/leakage=1.5"]
    assert strong["stopped"] and strong["edit_coverage"] < 0.5
    assert len(strong["warnings"]) == 1 and "outside the localized region" in strong["warnings"][0]
    assert strong["psnr_unedited"] == 120.0 and strong["gaussians_added"] == 0
    # The table names the first severity whose run fails (in-region PSNR under doing nothing + 1 dB;
    # at the quick run's 1x10 steps the milder severities may too, depending on the editor's draw),
    # and marks a stopped run as such.
    severities = ["0", "0.35", "1.5"]
    keys = ["add/regional-edit/leakage=0", "add/regional-edit/default", "add/regional-edit/leakage=1.5"]
    first = next(sev for sev, key in zip(severities, keys) if stability.fails(records[key]))
    assert payload["breaks"]["leakage"]["regional-edit"] == first + (" (stopped)" if first == "1.5" else "")
    for name in ("stability_region.png", "stability_unedited.png"):
        png = tmp_path / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5_000

    # An instruction about something the scene does not show: the relevance maps are noise, the
    # views disagree, and the run says so and takes the safe path.
    empty = records["empty/regional-edit/default"]
    assert empty["stopped"] == "views disagree" and empty["view_agreement"] < 0.3
    assert len(empty["warnings"]) == 1 and "the views disagree about the region" in empty["warnings"][0]
    assert empty["psnr_unedited"] == 120.0 and empty["gaussians_added"] == 0  # the source, unchanged
    edited = ply_arrays(Path(empty["trial"]) / "save" / "edited.ply")
    np.testing.assert_array_equal(np.stack([edited[k] for k in "xyz"], 1), make_edit("empty").source.means.detach().numpy())
