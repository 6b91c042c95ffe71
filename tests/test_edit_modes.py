"""`system.stop_after=localize` (a mode, not a threshold) and the one line a retired setting of an
older checkpoint stops a resume with."""
import pytest

from trial_helpers import launch, metrics_of


def test_stop_after_localize_writes_the_localization_figures_and_the_source_unchanged(tmp_path):
    m = metrics_of(launch(tmp_path, "localize-only", "system.stop_after=localize"))
    assert m["stopped"] == "stop_after=localize" and m["warnings"] == []
    for key in ("mask_iou", "mask_iou_seen", "mask_iou_exact_masks", "view_agreement", "view_weights"):
        assert key in m, key
    assert m["gaussians_added"] == 0 and m["psnr_unedited"] == 120.0 and "v_first" not in m


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
