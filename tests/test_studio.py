"""The studio (`launch.py --studio`) and the notebook steps under it (gs_regional.localize,
Localized.select, gs_regional.edit(selection=...)): the evidence a localization saves, the
selection re-made from it without the editor, the studio's edit against the command line's, and
the page itself in headless Chromium (skipped where viser, playwright or Chromium is absent)."""
import io
import sys
from contextlib import redirect_stderr

import numpy as np
import pytest
import torch

import gs_regional as gr
from trial_helpers import DEMO, launch, metrics_of, small_demo

PROMPT = "give him a mustache"


def small_overrides(name):
    """tests/data/small_demo.yaml as the API's `overrides` dict, with the run's name."""
    return {**dict(item.split("=", 1) for item in small_demo()), "name": name}


class UnetCount:
    """Counts the simulated editor's relevance and edit calls in this process (the UNet's work)."""

    def __init__(self, monkeypatch):
        from gs_regional.sim.editor import SimulatedEditor

        self.calls = 0
        for name in ("_relevance", "_edit"):
            real = getattr(SimulatedEditor, name)

            def counted(*args, _real=real, **kwargs):
                self.calls += 1
                return _real(*args, **kwargs)

            monkeypatch.setattr(SimulatedEditor, name, counted)


@pytest.fixture(scope="module")
def localized(tmp_path_factory):
    out = tmp_path_factory.mktemp("studio_localize")
    return out, gr.localize(config=DEMO, out=out, overrides=small_overrides("loc"))


# ----- the notebook steps -------------------------------------------------------------------------
def test_localize_keeps_the_evidence_and_select_remakes_the_selection(localized):
    out, loc = localized
    assert isinstance(loc, gr.Localized) and loc.trial == out / "loc" / "add"
    n = loc.source.num_gaussians
    assert n == 9765 and loc.selection.dtype == torch.bool and len(loc.selection) == n
    assert loc.metrics["stopped"] == "stop_after=localize" and loc.metrics["unet_evals"] > 0
    # The evidence: the lift's scores, its neighbourhood rows and the views' relevance masks.
    assert loc.scores.dtype == torch.float32 and loc.scores.shape == (n,)
    assert loc.neighbourhood.shape == (n, 16) and bool((loc.neighbourhood[:, 0] == torch.arange(n)).all())
    assert loc.threshold == 0.5 and len(loc.masks) == 6
    assert all(m.dtype == torch.bool and m.shape == (32, 32) and bool(m.any()) for m in loc.masks.values())
    with np.load(loc.trial / "save" / "localization.npz") as f:
        assert f["scores"].dtype == np.float32 and f["selected"].dtype == bool and f["neighbourhood"].dtype == np.int32
    # At the lift's own threshold the selection is the run's, exactly; other thresholds nest.
    assert 0 < loc.count < n
    assert torch.equal(loc.select(), loc.selection) and torch.equal(loc.select(loc.threshold), loc.selection)
    low, high = loc.select(0.3), loc.select(0.7)
    assert int(low.sum()) > loc.count > int(high.sum()) > 0
    assert bool((high <= loc.selection).all()) and bool((loc.selection <= low).all())
    # The same run's mask.ply holds exactly the selected Gaussians.
    assert gr.GaussianModel.from_ply(str(loc.trial / "save" / "mask.ply")).num_gaussians == loc.count


def test_select_costs_no_editor_call(localized, monkeypatch):
    _, loc = localized
    count = UnetCount(monkeypatch)
    counts = {t: int(loc.select(t).sum()) for t in (0.2, 0.4, 0.6, 0.8)}
    assert count.calls == 0
    assert sorted(counts.values(), reverse=True) == list(counts.values()) and len(set(counts.values())) == 4


def test_a_given_selection_is_saved_without_scores(localized):
    out, loc = localized
    from gs_regional.sim.scene import make_edit

    region = make_edit("add").region.numpy()
    given = gr.localize(config=DEMO, out=out, overrides={**small_overrides("loc-given"),
                                                         "system.selection_file": str(gr.api._write_selection(region, out))})
    assert given.scores is None and given.masks == {} and given.metrics["unet_evals"] == 0
    assert torch.equal(given.selection, torch.as_tensor(region)) and torch.equal(given.select(0.1), given.selection)
