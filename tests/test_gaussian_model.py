"""GaussianModel: construction, row operations with optimizers (geometry/rows.py), the densification
strategy (geometry/strategy.py), gradient masking, checkpoint resizing."""
import copy
import math

import numpy as np
import pytest
import torch

import gs_regional
from gs_regional.geometry import rows
from gs_regional.geometry.gaussian_model import PARAM_NAMES, ROW_STATE, GaussianModel, LearningRates
from gs_regional.geometry.strategy import DensifyStrategy, add_gradient_stats
from gs_regional.utils.sh import SH_C0


def make_model(n=12, degree=1, seed=0):
    g = torch.Generator().manual_seed(seed)
    k1 = (degree + 1) ** 2 - 1
    return GaussianModel.from_tensors(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacity_logits=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g),
        sh_rest=torch.randn(n, k1, 3, generator=g),
    )


def full_loss(model):
    """A loss that touches every parameter, so every row gets a non-zero gradient."""
    return sum((getattr(model, name) ** 2).sum() + getattr(model, name).sum() for name in PARAM_NAMES)


def make_adam(model):
    return torch.optim.Adam(model.optimizer_param_groups(spatial_scale=2.0), eps=1e-15)


def adam_step(model, opt):
    opt.zero_grad()
    full_loss(model).backward()
    opt.step()


def check_optimizer_state(model, opt):
    for group in opt.param_groups:
        p = group["params"][0]
        assert p is getattr(model, group["name"])  # the same Parameter object
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def check_buffers(model):
    n = model.num_gaussians
    for name in ROW_STATE:
        if name != "extras":
            assert getattr(model, name).shape == (n,), name
    assert model.extras.shape == (n, len(model.extra_names))


def test_registered_and_constructed_from_config(tmp_path):
    cls = gs_regional.find("gaussian-model")
    assert cls is GaussianModel
    m = make_model(5, degree=2)
    m.save_ply(tmp_path / "s.ply")
    loaded = cls({"ply": str(tmp_path / "s.ply"), "sh_degree": 0})
    assert loaded.sh_degree == 2 and len(loaded) == 5  # the file's degree wins
    assert torch.equal(loaded.sh_rest, m.sh_rest)
    assert loaded.source_path == str(tmp_path / "s.ply")
    assert len(cls()) == 0


def test_from_points_follows_3dgs_init():
    g = torch.Generator().manual_seed(2)
    xyz = torch.rand(300, 3, generator=g)
    rgb = torch.randint(0, 256, (300, 3), dtype=torch.uint8, generator=g)
    m = GaussianModel.from_points(xyz, rgb, sh_degree=3, opacity=0.1)
    assert m.sh_degree == 3 and m.sh_rest.shape == (300, 15, 3) and not m.sh_rest.any()
    torch.testing.assert_close(m.sh_dc.detach(), (rgb.float() / 255 - 0.5) / SH_C0)
    d2 = torch.cdist(xyz.double(), xyz.double()).fill_diagonal_(math.inf).pow(2).topk(3, largest=False).values
    expected = torch.log(torch.sqrt(d2.mean(1).clamp_min(1e-7))).float()
    torch.testing.assert_close(m.log_scales.detach(), expected[:, None].expand(-1, 3), rtol=1e-4, atol=1e-4)
    assert torch.equal(m.quats.detach(), torch.tensor([[1.0, 0, 0, 0]]).expand(300, 4))
    torch.testing.assert_close(m.opacities.detach(), torch.full((300,), 0.1))
    with pytest.raises(ValueError, match="rgb"):
        GaussianModel.from_points(xyz, rgb[:5])


def test_from_tensors_validates_shapes():
    with pytest.raises(ValueError, match="quats"):
        GaussianModel.from_tensors(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4), torch.zeros(4, 3))
    m = GaussianModel.from_tensors(torch.zeros(4, 3), torch.ones(4, 4), torch.zeros(4, 3), torch.zeros(4, 1),
                                   torch.zeros(4, 1, 3), mask=torch.tensor([1, 0, 1, 0]).bool(), generation=torch.ones(4))
    assert m.sh_degree == 0 and m.mask.tolist() == [True, False, True, False] and m.generation.dtype == torch.long


def test_select_is_a_detached_copy(tmp_path):
    m = make_model(10)
    m.mask[2:5] = True
    sel = m.select(m.mask)
    assert len(sel) == 3 and sel.mask.all() and sel.sh_degree == 1
    assert torch.equal(sel.means, m.means[2:5])
    with torch.no_grad():
        sel.means.add_(1.0)
    assert not torch.equal(sel.means, m.means[2:5])
    sel.save_ply(tmp_path / "mask.ply")
    assert len(GaussianModel.from_ply(tmp_path / "mask.ply")) == 3
    assert len(m.select(torch.tensor([0, 9]))) == 2


def test_prune_and_append_keep_parameters_and_fix_adam_state():
    m = make_model(12)
    params_before = [getattr(m, n) for n in PARAM_NAMES]
    opt = make_adam(m)
    adam_step(m, opt)
    exp_avg_before = opt.state[m.means]["exp_avg"].clone()

    keep = torch.ones(12, dtype=torch.bool)
    keep[[1, 5, 6]] = False
    assert rows.keep(m, keep, optimizer=opt) == 3
    assert len(m) == 9
    check_optimizer_state(m, opt)
    check_buffers(m)
    assert torch.equal(opt.state[m.means]["exp_avg"], exp_avg_before[keep])
    adam_step(m, opt)

    other = make_model(4, seed=5)
    added = rows.append(m, {n: getattr(other, n).detach() for n in PARAM_NAMES}, optimizer=opt, mask=True, generation=1)
    assert added == 4 and len(m) == 13
    check_optimizer_state(m, opt)
    check_buffers(m)
    assert not opt.state[m.quats]["exp_avg"][9:].any() and not opt.state[m.quats]["exp_avg_sq"][9:].any()
    assert m.mask.tolist() == [False] * 9 + [True] * 4 and m.generation[9:].tolist() == [1] * 4
    adam_step(m, opt)
    rows.append(m, other, optimizer=opt)  # from another model (its own mask/generation)
    adam_step(m, opt)
    check_optimizer_state(m, opt)
    assert [getattr(m, n) for n in PARAM_NAMES] == params_before
    with pytest.raises(ValueError, match="SH degree"):
        rows.append(m, make_model(2, degree=0))


def test_a_graph_kept_alive_across_a_row_change_does_not_break_the_next_backward():
    """A render (or any output) someone keeps holds the parameters' gradient accumulators, which
    recorded the old number of rows; after keep, append, duplicate or a state-dict resize the next
    backward must still work and give gradients of the new shape (seen on an H200: an edit whose
    depth step appended Gaussians failed its first refinement step)."""
    m = make_model(12)
    m.set_trainable_mask(torch.ones(12, dtype=torch.bool))  # the gradient hooks must survive too
    opt = make_adam(m)
    kept = []

    def step():
        out = m.sh[:, None] * m.means.sum(-1)[:, None, None, None]  # an unsqueeze, like a renderer's
        kept.append(out)
        opt.zero_grad()
        (out.sum() + full_loss(m)).backward()
        opt.step()
        assert all(getattr(m, n).grad.shape == getattr(m, n).shape for n in PARAM_NAMES)

    step()
    rows.keep(m, torch.arange(12) % 4 != 0, optimizer=opt)
    m.set_trainable_mask(torch.ones(9, dtype=torch.bool))
    step()
    other = make_model(3, seed=4)
    rows.append(m, {n: getattr(other, n).detach() for n in PARAM_NAMES}, optimizer=opt, trainable=True)
    step()
    rows.duplicate(m, torch.tensor([0, 1]), optimizer=opt)
    step()
    assert len(m) == 14
    m.load_state_dict(copy.deepcopy(make_model(5, seed=6).state_dict()))
    opt = make_adam(m)
    step()
    check_optimizer_state(m, opt)


def _densify_setup():
    """12 Gaussians: 0-1 small & high gradient (clone), 2-3 large & high gradient (split),
    4 faint (prune), the rest quiet."""
    m = make_model(12)
    with torch.no_grad():
        m.log_scales[:] = math.log(0.001)
        m.log_scales[2:4] = math.log(0.5)
        m.opacity_logits[:] = 2.0
        m.opacity_logits[4] = -10.0
    grad = torch.zeros(12, 2)
    grad[0:4, 0] = 1.0
    grad[1, 0] = 2.0
    for _ in range(2):
        add_gradient_stats(m, grad, torch.ones(12, dtype=torch.bool))
    return m


def test_densify_and_prune_with_adam():
    m = _densify_setup()
    m.mask[0:3] = True
    m.generation[3] = 2
    opt = make_adam(m)
    adam_step(m, opt)
    parent_scales = m.scales[2:4].detach().clone()
    parent_means = m.means[2:4].detach().clone()
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, scene_extent=1.0, optimizer=opt)
    assert out == {"cloned": 2, "split": 2, "pruned": 1}
    assert len(m) == 12 + 2 + 2 - 1  # +2 clones, +4 split children -2 parents, -1 faint
    check_optimizer_state(m, opt)
    check_buffers(m)
    assert not m.grad_accum.any() and not m.grad_count.any()
    # children come last: clones of 0, 1 then split samples of 2, 3, 2, 3
    children = slice(len(m) - 4, len(m))
    torch.testing.assert_close(m.scales[children].detach(), parent_scales.repeat(2, 1) / 1.6)
    assert ((m.means[children].detach() - parent_means.repeat(2, 1)).norm(dim=1) < 5 * 0.5).all()
    assert m.mask[-6:].tolist() == [True, True, True, False, True, False]  # inherited
    assert m.generation[-6:].tolist() == [0, 0, 0, 2, 0, 2]
    assert (m.opacities > 0.5).all()
    adam_step(m, opt)


def test_densify_only_mask_and_budget():
    m = _densify_setup()
    m.mask[[1, 3]] = True  # 0 (clone) and 2 (split) and 4 (faint) are outside the edit
    m.set_trainable_mask("editable")
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0)
    assert out == {"cloned": 1, "split": 1, "pruned": 0}
    assert len(m) == 12 + 1 + 1
    assert m.opacities.min() < 0.01  # the faint unmasked Gaussian survives

    m = _densify_setup()
    m.mask[[1, 3]] = True
    m.set_trainable_mask("editable")
    out = DensifyStrategy(grad_threshold=0.5, only_trainable=False).densify_and_prune(m, 1.0)
    assert out == {"cloned": 2, "split": 2, "pruned": 1}  # every Gaussian when told so

    m = _densify_setup()
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0, max_gaussians=13)
    assert out["cloned"] + out["split"] == 1
    assert out["cloned"] == 1  # Gaussian 1 has the highest gradient
    assert len(m) <= 13


def test_densify_prunes_large_on_screen_and_batched_stats():
    m = make_model(6)
    with torch.no_grad():
        m.log_scales[:] = math.log(0.001)
        m.opacity_logits[:] = 2.0
    grads = torch.zeros(2, 6, 2)
    grads[0, 0] = torch.tensor([3.0, 4.0])  # norm 5, in view 0 only
    vis = torch.tensor([[True] * 6, [True, False, True, True, True, True]])
    add_gradient_stats(m, grads, vis, radii=torch.tensor([[1.0, 99.0, 1, 1, 1, 1], [2.0, 500.0, 1, 1, 1, 1]]))
    assert m.grad_accum[0].item() == pytest.approx(5.0) and m.grad_count.tolist() == [2, 1, 2, 2, 2, 2]
    assert m.max_radii2d[1].item() == 99.0  # not visible in view 1
    strategy = DensifyStrategy(grad_threshold=10.0, max_screen_size=50)
    assert strategy.densify_and_prune(copy.deepcopy(m), 1.0) == {"cloned": 0, "split": 0, "pruned": 0}
    out = strategy.densify_and_prune(m, 1.0, prune_large=True)
    assert out == {"cloned": 0, "split": 0, "pruned": 1} and len(m) == 5
    with pytest.raises(ValueError, match="means2d_grad"):
        add_gradient_stats(m, torch.zeros(4, 2), torch.ones(4, dtype=torch.bool))


def test_every_registered_row_buffer_follows_every_row_operation(monkeypatch):
    """A per-row buffer added to ROW_STATE follows keep, append, duplicate, densification, select
    and checkpoint resizing without any other change (the registry is the only list of them)."""
    from gs_regional.geometry.gaussian_model import RowState

    monkeypatch.setitem(ROW_STATE, "votes", RowState(torch.float32, -1.0, inherit=True))
    m = _densify_setup()
    assert m.votes.shape == (12,)
    m.votes.copy_(torch.arange(12.0))
    opt = make_adam(m)
    adam_step(m, opt)
    DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0, optimizer=opt)
    # parents 0..11 minus the split 2, 3 and the faint 4; then clones of 0, 1 and children of 2, 3, 2, 3
    assert m.votes.tolist() == [0, 1, 5, 6, 7, 8, 9, 10, 11, 0, 1, 2, 3, 2, 3]
    assert m.source_index.tolist() == m.votes.long().tolist()  # the source rows travel the same way
    rows.append(m, make_model(2, seed=3), optimizer=opt)
    assert m.votes[-2:].tolist() == [-1, -1] and m.source_index[-2:].tolist() == [-1, -1]
    check_optimizer_state(m, opt)
    check_buffers(m)
    assert m.select(torch.tensor([9, 15])).votes.tolist() == [0, -1]
    small = make_model(3)
    small.load_state_dict(m.state_dict())
    assert torch.equal(small.votes, m.votes)


def test_source_index_follows_rows_and_finds_the_source_region():
    """Row positions change under densify and prune; source_index does not lose track of the
    source rows, so the localized region of the source is found wherever its rows went."""
    n = 12
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(4))
    m = _densify_setup().select(perm)  # rows in a scattered order, as in a real file
    assert m.source_index.tolist() == perm.tolist()  # select keeps where each row came from
    m = m.select(torch.arange(n))
    assert m.source_index.tolist() == perm.tolist()
    fresh = make_model(n)
    assert fresh.source_index.tolist() == list(range(n))  # a new model is its own source
    region = torch.zeros(n, dtype=torch.bool)
    region[[1, 2, 4, 7]] = True  # source rows: a clone, a split parent, a faint one, a quiet one
    m.mask.copy_(region[m.source_index])
    m.set_trainable_mask("editable")
    rows.append(m, make_model(3, seed=2), mask=True, generation=1)  # Gaussians added by the edit
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0)
    assert out == {"cloned": 1, "split": 1, "pruned": 1}
    assert torch.equal(rows.source_rows(m, m.mask, n), region & (torch.arange(n) != 4))  # the faint one is gone
    assert (m.source_index[m.generation == 1] == -1).all()
    # The way back: every row descending from a selected source row (clones and split halves too),
    # none of the added ones.
    back = rows.of_source(m, region)
    assert torch.equal(rows.source_rows(m, back, n), region & (torch.arange(n) != 4)) and not back[m.generation == 1].any()
    assert not torch.equal(m.mask[:n], region)  # what indexing by position would have used
    with pytest.raises(ValueError, match="out of range"):
        rows.source_rows(m, m.mask, 3)


def test_densify_strategy_schedule_and_caps():
    s = DensifyStrategy(start=100, stop=1000, every=100, opacity_reset_every=300)
    assert [t for t in range(0, 1200, 50) if s.densifies_at(t)] == list(range(100, 1000, 100))
    assert not s.densifies_at(900, last_step=900)  # the last step's new Gaussians would not be trained
    assert [t for t in range(0, 1200, 100) if s.resets_opacity_at(t)] == [300, 600, 900]
    assert s.collects_stats(999) and not s.collects_stats(1000)
    assert not DensifyStrategy(enabled=False).collects_stats(0)
    edit = DensifyStrategy(start=0, stop=None, every=50, max_gaussians=None, budget=20)
    assert [t for t in range(100) if edit.densifies_at(t, last_step=99)] == [50]
    assert edit.max_count(base_count=100) == 120 and DensifyStrategy(max_gaussians=None).max_count() is None
    assert DensifyStrategy(max_gaussians=110, budget=20).max_count(base_count=100) == 110
    with pytest.raises(ValueError, match="base_count"):
        edit.max_count()
    assert not s.prunes_large_at(400) and DensifyStrategy(max_screen_size=20, opacity_reset_every=300).prunes_large_at(301)
    from gs_regional.config import ConfigError

    with pytest.raises(ConfigError, match="system.densify.every"):
        DensifyStrategy(every=0).check("system.densify")
    with pytest.raises(ConfigError, match="system.densify.rounds"):
        DensifyStrategy(every=None, rounds=0).check("system.densify")


def test_densify_rounds_do_not_grow_with_the_schedule():
    """`every: null`: `rounds` evenly spaced densifications over the caller's schedule, so a cycle
    twice as long trains longer between the same rounds instead of densifying twice as often."""
    once = DensifyStrategy(start=0, stop=None, every=None, rounds=1)
    assert [t for t in range(60) if once.densifies_at(t, last_step=59)] == [30]
    assert [t for t in range(120) if once.densifies_at(t, last_step=119)] == [60]
    three = DensifyStrategy(start=0, stop=None, every=None, rounds=3)
    assert [t for t in range(100) if three.densifies_at(t, last_step=99)] == [25, 50, 75]
    assert [t for t in range(3) if three.densifies_at(t, last_step=2)] == [1]  # too short for three: no repeats
    with pytest.raises(ValueError, match="last_step"):
        once.densifies_at(30)
    from gs_regional.systems.regional_edit import RegionalEdit

    assert RegionalEdit.Config().densify.every is None and RegionalEdit.Config().densify.rounds == 1


def test_refine_densifies_when_due_with_the_budget():
    m = _densify_setup()
    strategy = DensifyStrategy(start=0, stop=None, every=10, opacity_reset_every=0, max_gaussians=None, budget=1)
    assert strategy.refine(m, 5, scene_extent=1.0, base_count=12) is None and len(m) == 12
    out = strategy.refine(m, 10, scene_extent=1.0, base_count=12)
    assert out == {"cloned": 1, "split": 0, "pruned": 1} and len(m) == 12  # one new, one faint pruned


def test_reset_opacity_clamps_and_zeroes_state():
    m = make_model(8)
    opt = make_adam(m)
    adam_step(m, opt)
    m.mask[:4] = True
    before = m.opacities.detach().clone()
    rows.reset_opacity(m, 0.01, optimizer=opt, rows=m.mask.clone())
    assert (m.opacities[:4] <= 0.01 + 1e-6).all()
    torch.testing.assert_close(m.opacities[4:].detach(), before[4:])
    st = opt.state[m.opacity_logits]
    assert not st["exp_avg"][:4].any() and st["exp_avg"][4:].all()
    rows.reset_opacity(m, optimizer=opt)
    assert (m.opacities <= 0.01 + 1e-6).all()


def _row_has_grad(p):
    return p.grad.reshape(p.shape[0], -1).abs().sum(1) > 0


def test_gradient_masking_covers_every_parameter_and_survives_changes():
    m = make_model(10, degree=1)
    trainable = torch.zeros(10, dtype=torch.bool)
    trainable[[0, 3, 4]] = True
    m.set_trainable_mask(trainable)
    full_loss(m).backward()
    for name in PARAM_NAMES:
        assert torch.equal(_row_has_grad(getattr(m, name)), trainable), name

    # explicit rows follow prune and append (new rows trainable)
    keep = torch.ones(10, dtype=torch.bool)
    keep[3] = False
    rows.keep(m, keep)
    rows.append(m, make_model(2, seed=9))
    full_loss(m).backward()
    expected = torch.tensor([True, False, False, True] + [False] * 5 + [True, True])  # old 4 is now 3
    for name in PARAM_NAMES:
        assert torch.equal(_row_has_grad(getattr(m, name)), expected), name

    # the "editable" rule is evaluated at backward time: mask | generation > 0
    m.zero_grad(set_to_none=True)
    m.set_trainable_mask("editable")
    m.mask.zero_()
    m.mask[1] = True
    rows.append(m, make_model(3, seed=4), generation=1)
    opt = make_adam(m)
    out = copy.deepcopy(m)  # hooks are re-registered on the copy's parameters
    for model in (m, out):
        model.zero_grad(set_to_none=True)
        full_loss(model).backward()
        expected = torch.zeros(len(model), dtype=torch.bool)
        expected[1] = True
        expected[-3:] = True
        for name in PARAM_NAMES:
            assert torch.equal(_row_has_grad(getattr(model, name)), expected), name
    before = m.means.detach().clone()
    opt.step()
    assert torch.equal(m.means[0], before[0]) and not torch.equal(m.means[1], before[1])

    m.set_trainable_mask(None)
    m.zero_grad(set_to_none=True)
    full_loss(m).backward()
    assert _row_has_grad(m.quats).all()
    with pytest.raises(ValueError, match="shape"):
        m.set_trainable_mask(torch.ones(3, dtype=torch.bool))


def test_state_dict_load_resizes_and_keeps_parameters():
    big = make_model(10, degree=1)
    big.mask[2] = True
    big.generation[7] = 1
    add_gradient_stats(big, torch.ones(10, 2), torch.ones(10, dtype=torch.bool))
    big.set_trainable_mask("editable")
    state = big.state_dict()

    small = make_model(3, degree=0, seed=3)
    params = [getattr(small, n) for n in PARAM_NAMES]
    opt = make_adam(small)
    small.load_state_dict(state)
    assert len(small) == 10 and small.sh_degree == 1
    assert [getattr(small, n) for n in PARAM_NAMES] == params
    assert [g["params"][0] for g in opt.param_groups] == params
    for key, value in state.items():
        if torch.is_tensor(value):
            assert torch.equal(small.state_dict()[key], value), key
    assert small.trainable_rows().tolist() == big.editable_rows().tolist()
    adam_step(small, opt)  # the optimizer works on the resized parameters


def test_optimizer_param_groups():
    m = make_model(3)
    groups = m.optimizer_param_groups({"sh_dc": 0.01}, spatial_scale=5.0)
    by_name = {g["name"]: g for g in groups}
    assert set(by_name) == set(PARAM_NAMES)
    assert by_name["means"]["lr"] == pytest.approx(LearningRates().means * 5.0)
    assert by_name["sh_dc"]["lr"] == 0.01 and by_name["sh_rest"]["lr"] == pytest.approx(2.5e-3 / 20)
    assert by_name["quats"]["params"][0] is m.quats
    with pytest.raises(ValueError, match="colour"):
        m.optimizer_param_groups({"colour": 1.0})
    lr = LearningRates(quats=0.5)  # the dataclass the systems' `system.lr` parses into
    assert {g["name"]: g["lr"] for g in m.optimizer_param_groups(lr)}["quats"] == 0.5


def test_added_only_parameters_train_on_added_rows_alone():
    """An edit that may change the shape keeps the selected source Gaussians' place, size and
    opacity (RegionalEdit's refine.source_fixed): their colours train, those parameters only on
    the rows the edit added."""
    from gs_regional.geometry import rows
    from gs_regional.sim.scene import make_edit

    model = make_edit("add").source
    model.mask[:50] = True
    n = model.num_gaussians
    rows.append(model, {k: getattr(model, k).detach()[:10].clone() for k in
                        ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")}, generation=1)
    model.set_trainable_mask("editable")
    model.set_added_only(["means", "quats", "log_scales", "opacity_logits"])
    loss = sum((getattr(model, k) ** 2).sum() for k in ("means", "quats", "log_scales", "opacity_logits", "sh_dc"))
    loss.backward()
    for name in ("means", "quats", "log_scales", "opacity_logits"):
        grad = getattr(model, name).grad.reshape(n + 10, -1)
        assert not bool(grad[:n].any()) and bool(grad[n:].any(1).all()), name
    assert bool(model.sh_dc.grad[:50].any(1).all()) and not bool(model.sh_dc.grad[50:n].any())
    # the setting survives a checkpoint
    state = model.get_extra_state()
    assert state["added_only"] == ["means", "quats", "log_scales", "opacity_logits"]
    with pytest.raises(ValueError, match="unknown parameters"):
        model.set_added_only(["scales"])


def test_restore_puts_rows_back_to_their_source_and_stops_adam_moving_them():
    """A recolour's gate hands rows back to their source colours: the rows take the source's
    values through `source_index` (wherever they are now), their Adam moments are zeroed, so the
    next masked step leaves them there, and every other row and parameter is untouched."""
    source = make_model()
    model = copy.deepcopy(source)
    opt = make_adam(model)
    for _ in range(3):
        adam_step(model, opt)
    rows.keep(model, torch.arange(12) != 4, opt)  # rows move: row k >= 4 is source row k + 1
    back = torch.zeros(11, dtype=torch.bool)
    back[[0, 5, 9]] = True
    before = {name: getattr(model, name).detach().clone() for name in PARAM_NAMES}
    assert rows.restore(model, source, back, ("sh_dc", "sh_rest"), opt) == 3
    for name in ("sh_dc", "sh_rest"):
        p = getattr(model, name)
        assert torch.equal(p.detach()[back], getattr(source, name).detach()[[0, 6, 10]])
        assert torch.equal(p.detach()[~back], before[name][~back])
        assert not opt.state[p]["exp_avg"][back].any() and not opt.state[p]["exp_avg_sq"][back].any()
    assert torch.equal(model.means.detach(), before["means"])
    model.set_trainable_mask(~back)
    adam_step(model, opt)
    assert torch.equal(model.sh_dc.detach()[back], source.sh_dc.detach()[[0, 6, 10]])


def test_an_addition_densifies_only_the_gaussians_it_added_once_it_has_some():
    """A selected source Gaussian of an addition keeps its position (refine.source_fixed); split
    or cloned, its children would be free rows of the edit carved out of the fixed surface beside
    the object. Once depth has added Gaussians only they densify; before (depth placed none) the
    selection densifies to grow the object."""
    from gs_regional.geometry.gaussian_model import EDITABLE
    from gs_regional.stages.ablation import AblationConfig
    from gs_regional.stages.strategies import Addition, RefineConfig

    addition = Addition(RefineConfig(), AblationConfig())
    m = _densify_setup()  # rows 0, 1 cloned (small), 2, 3 split (large), by their gradients
    m.mask[0:4] = True
    m.generation[[1, 3]] = 1  # two of them the edit added
    m.set_trainable_mask(EDITABLE)
    sources = m.means.detach()[[0, 2]].clone()
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0, grow=addition.growable(m))
    assert out["cloned"] == 1 and out["split"] == 1  # the added rows 1 and 3
    assert int((m.generation == 0).sum()) == 12 - 2  # every source row kept, none split
    assert all(bool((m.means.detach() == p).all(1).any()) for p in sources)

    m = _densify_setup()
    m.mask[0:4] = True
    m.set_trainable_mask(EDITABLE)
    assert addition.growable(m) is None  # nothing added yet: the selection grows the object
    out = DensifyStrategy(grad_threshold=0.5).densify_and_prune(m, 1.0, grow=addition.growable(m))
    assert out["cloned"] == 2 and out["split"] == 2
