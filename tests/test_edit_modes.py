"""`system.stop_after=localize` (a mode, not a threshold) and the one line a retired setting of an
older checkpoint stops a resume with."""
import pytest

from trial_helpers import launch, metrics_of


def test_stop_after_localize_writes_the_localization_figures_and_the_source_unchanged(tmp_path):
    trial = launch(tmp_path, "localize-only", "system.stop_after=localize")
    m = metrics_of(trial)
    assert m["stopped"] == "stop_after=localize" and m["warnings"] == []
    for key in ("mask_iou", "mask_iou_seen", "mask_iou_exact_masks", "view_agreement", "view_weights"):
        assert key in m, key
    assert m["gaussians_added"] == 0 and m["psnr_unedited"] == 120.0 and "v_first" not in m
    # scripts/relift.py lifts the saved masks again: at the method's edge ratio it finds the run's figures
    from gs_regional.bench.relift import relift
    from gs_regional.stages.localize import EDGE_COLOUR_RATIO

    again = relift(str(trial), [EDGE_COLOUR_RATIO, 0.0])
    assert again[EDGE_COLOUR_RATIO]["masks"]["mask_iou"] == pytest.approx(m["mask_iou"], abs=1e-9)
    assert again[EDGE_COLOUR_RATIO]["exact"]["mask_iou"] == pytest.approx(m["mask_iou_exact_masks"], abs=1e-9)
    assert again[0.0]["masks"]["mask_recall"] >= again[EDGE_COLOUR_RATIO]["masks"]["mask_recall"]
    # --grow: the exact masks grown by a pixel reach past the part: they find at least its Gaussians
    # the exact masks find, and only with --grow are they lifted
    grown = relift(str(trial), [0.0], grow=1)[0.0]
    assert grown["grown"]["mask_recall"] >= grown["exact"]["mask_recall"] and "grown" not in again[0.0]
    # each case at its best threshold: the run's own threshold among them gives at least the run's IoU
    import numpy as np

    own = float(np.load(trial / "save" / "localization.npz")["threshold"])
    best = relift(str(trial), [EDGE_COLOUR_RATIO], thresholds=[own, 0.95])[EDGE_COLOUR_RATIO]
    assert best["best_masks"][0] >= m["mask_iou"] - 1e-9 and best["best_masks"][1] in (own, 0.95)
    assert relift(str(trial), [EDGE_COLOUR_RATIO], thresholds=[own])[EDGE_COLOUR_RATIO]["best_exact"] == (
        pytest.approx(m["mask_iou_exact_masks"], abs=1e-9), own)
    # --breakdown: every false positive and every miss falls in exactly one of its reasons, and the
    # counts give back the run's precision and recall
    from gs_regional.bench.relift import breakdown

    b = breakdown(str(trial))
    for group in ("false_positives", "misses"):
        assert sum(b[group][k] for k in ("unseen", "covered", "partly", "pooled")) == b[group]["all"]
    fp, miss = b["false_positives"]["all"], b["misses"]["all"]
    assert (b["selected"] - fp) / b["selected"] == pytest.approx(m["mask_precision"], abs=1e-9)
    assert (b["truth"] - miss) / b["truth"] == pytest.approx(m["mask_recall"], abs=1e-9)
    assert 0 <= b["straddlers"]["truth"] <= b["straddlers"]["all"] <= b["selected"]
    # --exact: the same of the exact masks' lift, whose counts give back the run's figures from them;
    # the truth shows more inside its own masks than what they take with it
    e = breakdown(str(trial), exact=True)
    for group in ("false_positives", "misses"):
        assert sum(e[group][k] for k in ("unseen", "covered", "partly", "pooled")) == e[group]["all"]
    precision = (e["selected"] - e["false_positives"]["all"]) / e["selected"]
    assert precision == pytest.approx(m["mask_precision_exact_masks"], abs=1e-9)
    assert (e["truth"] - e["misses"]["all"]) / e["truth"] == pytest.approx(m["mask_recall_exact_masks"], abs=1e-9)
    assert e["inside_px"]["truth"] > e["inside_px"]["false_positives"] >= 0


def test_a_checkpoint_written_with_a_retired_setting_stops_the_resume_with_one_line():
    from gs_regional.config import ConfigError, check_saved_config
    from gs_regional.systems.regional_edit import RegionalEdit

    cfg = RegionalEdit.Config()
    same = {"initialize": True, "refine": {"first_cycle_first_view": "skip", "constant_t": None},
            "localization": {"reweight_iters": 2}}
    check_saved_config(same, RegionalEdit.Config, cfg, "system")  # what the method now does: resumes
    with pytest.raises(ConfigError, match="system.refine.first_cycle_first_view='reedit', a setting that was removed"):
        check_saved_config({"refine": {"first_cycle_first_view": "reedit"}}, RegionalEdit.Config, cfg, "system")
    with pytest.raises(ConfigError, match="system.initialize=False, which has moved to system.ablation.initialize"):
        check_saved_config({"initialize": False}, RegionalEdit.Config, cfg, "system")
