"""gs_regional.edit: the edit from Python is launch.py's run (README "From Python")."""
import numpy as np
import pytest
import torch

import gs_regional as gr
from gs_regional.config import ConfigError
from trial_helpers import DEMO, metrics_of, small_demo


def small_overrides(name):
    """tests/data/small_demo.yaml as gs_regional.edit's `overrides` dict, with the run's name."""
    return {**dict(item.split("=", 1) for item in small_demo()), "name": name}


@pytest.fixture(scope="module")
def api_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("api_edit")
    return out, gr.edit(config=DEMO, out=out, overrides=small_overrides("small-demo"))


def test_edit_from_python_gives_the_command_lines_edit(api_run, small_demo_run):
    out, result = api_run
    assert isinstance(result, gr.EditResult) and result.trial == out / "small-demo" / "add"
    assert result.metrics == metrics_of(result.trial)
    cli = metrics_of(small_demo_run)
    for key in ("gaussians_before", "gaussians_after", "mask_iou"):
        assert result.metrics[key] == cli[key], key
    psnrs = [k for k in cli if k.startswith("psnr") and isinstance(cli[k], float)]
    assert psnrs
    for key in psnrs:
        assert abs(result.metrics[key] - cli[key]) <= 0.05, key
    assert result.model.num_gaussians == result.metrics["gaussians_after"]
    assert result.selection.dtype == torch.bool and len(result.selection) == result.metrics["gaussians_before"]
    assert int(result.selection.sum()) > 0
    # The trial's command line is launch.py's, with the API's keys as overrides.
    assert "launch.py" in (result.trial / "cmd.txt").read_text()


def test_a_given_selection_is_the_edited_region(api_run):
    from gs_regional.sim.scene import make_edit

    out, _ = api_run
    truth = make_edit("add")
    region = truth.region.numpy()
    result = gr.edit(config=DEMO, out=out, selection=region, overrides=small_overrides("given"))
    assert torch.equal(result.selection, torch.as_tensor(region))
    assert result.metrics["mask_iou"] >= 0.999  # the true region, selected as given
    # Recorded in the trial's config: the command line in cmd.txt re-runs the same edit.
    parsed = (result.trial / "configs" / "parsed.yaml").read_text()
    assert "selection_file:" in parsed and "selections/" in parsed
    # Only the selection changes: the source rows outside it keep their place and colour.
    with np.load(result.trial / "save" / "edit_mask.npz") as f:
        gen, src = torch.as_tensor(f["generation"]), torch.as_tensor(f["source_index"]).long()
    outside = (gen == 0) & ~result.selection[src.clamp_min(0)]
    assert int(outside.sum()) > 0.5 * (~result.selection).sum()
    source = truth.source
    assert torch.allclose(result.model.means[outside], source.means[src[outside]], atol=1e-6)
    assert torch.allclose(result.model.sh_dc[outside], source.sh_dc[src[outside]], atol=1e-6)


def test_a_bad_override_key_is_a_config_error_naming_it(tmp_path):
    with pytest.raises(ConfigError, match="refine.cyclez"):
        gr.edit(config=DEMO, out=tmp_path, overrides={**small_overrides("bad"), "system.refine.cyclez": 1})


def test_a_selection_of_the_wrong_length_names_both_counts(tmp_path):
    # The demo's source scene has 9,765 Gaussians.
    with pytest.raises(ConfigError, match=r"selection_file .*: 5 entries.* 9,765 Gaussians"):
        gr.edit(config=DEMO, out=tmp_path, selection=np.ones(5, bool), overrides=small_overrides("short"))
