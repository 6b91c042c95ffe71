"""The first-view choice and the safe stop (gs_regional/stages/first_view.py) as plain functions:
known answers on three synthetic views, no system, no Lightning."""
import torch

from gs_regional.stages.first_view import check_edit, choose_first_view, stop_message

H = W = 32


def _views(inside):
    """Three views of a grey scene whose selection is a square at the centre; `inside[v]`: whether
    view v's full edit paints the square (True) or a square as large in a corner (False)."""
    source = torch.full((H, W, 3), 0.5)
    region = torch.zeros(H, W, dtype=torch.bool)
    region[12:20, 12:20] = True
    edits = {}
    for v, ok in enumerate(inside):
        out = source.clone()
        if ok:
            out[12:20, 12:20] = torch.tensor([0.9, 0.1, 0.1])
        else:
            out[0:8, 0:8] = torch.tensor([0.9, 0.1, 0.1])
        edits[v] = out
    return source, region, edits


def _choose(inside, min_edit_coverage=0.5):
    source, region, edits = _views(inside)
    views = list(range(len(inside)))
    edited = []

    def edit(v):
        edited.append(v)
        return edits[v]

    first = choose_first_view(
        views, torch.full((len(views),), 64.0), {v: region for v in views}, [region] * len(views), 0, edit,
        lambda v, out: check_edit(v, out, source, region, torch.ones(H, W), torch.ones(H, W)), min_edit_coverage)
    return first, edited


def test_an_edit_in_the_selection_goes_on_from_the_first_view():
    first, edited = _choose([True, True, True])
    assert first.view == 0 and not first.stop and edited == [0]
    assert first.decided is first.checks[0] and first.decided.coverage > 0.9
    assert first.checks[0].as_dict()["decides"] is True and "too_small_to_judge" not in first.checks[0].as_dict()


def test_an_edit_elsewhere_in_every_view_stops_with_one_message():
    first, edited = _choose([False, False, False])
    assert first.stop and edited == [0, 1]  # the second view is edited too: one view never decides alone
    assert first.decided.coverage < 0.1
    assert "system.localization.min_edit_coverage=0.5" in stop_message(first, 0.5)


def test_a_first_edit_placed_elsewhere_is_outvoted_by_two_views_that_agree():
    first, edited = _choose([False, True, True])
    assert not first.stop and first.view == 1 and edited == [0, 1, 2]
    assert first.decided.view == 1 and len(first.checks) == 3


def test_a_coverage_check_of_zero_never_stops():
    first, _ = _choose([False, False, False], min_edit_coverage=0.0)
    assert not first.stop and first.view == 0
