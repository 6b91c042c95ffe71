"""Voxel-grid kNN and radius queries against brute force, the connected pieces of a kNN graph against a
breadth-first search, and the localization that uses them."""
import math

import pytest
import torch

from gs_regional.stages.localize import expand_selection, knn_pool, neighbourhoods
from gs_regional.geometry.neighbors import components, knn, quantile_box, within_radius


def _sq_dists(a, b):
    # the same float32 arithmetic as the grid search, so distances compare exactly
    return ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)


def _brute_knn(x, k):
    d = _sq_dists(x, x)
    d.fill_diagonal_(math.inf)
    return d.sort(1)  # all of them: the (k+1)-th tells whether the k-th is tied


def _clouds():
    g = torch.Generator().manual_seed(0)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    n = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return {
        "uniform": r(1500, 3),
        # every point 7 times: more duplicates than some k, so ties at distance 0
        "duplicates": r(200, 3).repeat(7, 1),
        # a dense blob inside a sparse cloud: per-point cell sizes 4 orders of magnitude apart
        "clustered": torch.cat([n(1000, 3) * 1e-3, n(500, 3) * 10]),
        "anisotropic": r(1500, 3) * torch.tensor([1000.0, 1.0, 1e-3]),
        "far_from_origin": r(800, 3) + 1e4,
        "integer_grid": torch.stack(torch.meshgrid(*[torch.arange(9.0)] * 3, indexing="ij"), -1).reshape(-1, 3),
        "few_points": r(5, 3),
    }


@pytest.mark.parametrize("name", list(_clouds()))
@pytest.mark.parametrize("k", [1, 16, 40])
def test_knn_equals_brute_force(name, k):
    x = _clouds()[name]
    n = x.shape[0]
    d, i = knn(x, k, max_pairs=1 << 14)  # small blocks: the chunking is exercised too
    kk = min(k, n - 1)
    assert d.shape == i.shape == (n, kk) and i.dtype == torch.long
    ref_d, ref_i = _brute_knn(x, k)
    # distances: bit-exact, ascending
    assert torch.equal(d, ref_d[:, :kk])
    # indices: other points, no repeats, at the distances reported
    assert not (i == torch.arange(n)[:, None]).any()
    assert (i.sort(1).values.diff(dim=1) > 0).all()
    assert torch.equal(_sq_dists(x, x).gather(1, i), d)
    # Ties at the k-th distance may be broken either way; elsewhere the neighbour set is exact.
    untied = ref_d[:, kk - 1] < ref_d[:, kk] if kk < n - 1 else torch.ones(n, dtype=torch.bool)
    assert torch.equal(i[untied].sort(1).values, ref_i[untied, :kk].sort(1).values)


def test_knn_degenerate_inputs():
    assert knn(torch.zeros(0, 3), 4)[0].shape == (0, 0)
    assert knn(torch.zeros(1, 3), 4)[1].shape == (1, 0)
    same = torch.full((30, 3), 5.0)  # all identical: every neighbour at 0
    d, i = knn(same, 3)
    assert not d.any() and not (i == torch.arange(30)[:, None]).any()
    # a squared distance beyond float32's range: still the right (inf) answer, no crash
    d, i = knn(torch.tensor([[0.0, 0, 0], [1e30, 0, 0], [1.0, 0, 0]]), 1)
    assert d[:, 0].tolist() == [1.0, math.inf, 1.0] and i[0, 0] == 2 and i[2, 0] == 0


@pytest.mark.parametrize("name", ["uniform", "clustered", "anisotropic", "integer_grid", "duplicates"])
@pytest.mark.parametrize("radius", [0.0, 1e-3, 0.05, 1.0, 50.0])
def test_within_radius_equals_brute_force(name, radius):
    x = _clouds()[name]
    g = torch.Generator().manual_seed(1)
    seeds = x[torch.rand(x.shape[0], generator=g) < 0.05]
    got = within_radius(x, seeds, radius, max_pairs=1 << 12)
    # inclusive: on the integer grid many points lie at exactly 1.0
    ref = (_sq_dists(x, seeds) <= radius**2).any(1)
    assert torch.equal(got, ref)


def test_within_radius_edge_cases():
    x = torch.tensor([[0.0, 0, 0], [3.0, 4, 0], [1e30, 0, 0]])
    seeds = x[:1]
    assert within_radius(x, seeds, 5.0).tolist() == [True, True, False]
    assert within_radius(x, seeds, 4.999).tolist() == [True, False, False]
    assert within_radius(x, seeds[:0], 5.0).tolist() == [False] * 3
    assert within_radius(x[:0], seeds, 5.0).shape == (0,)


def _old_knn_pool(means, num, den, k):
    """The all-pairs version this module replaced (topk of cdist)."""
    idx = torch.cdist(means.double(), means.double()).topk(k, largest=False).indices
    return num[idx].sum(1), den[idx].sum(1)


def test_knn_pool_matches_all_pairs_pooling():
    g = torch.Generator().manual_seed(2)
    means = torch.randn(700, 3, generator=g)
    num, den = torch.rand(700, generator=g), torch.rand(700, generator=g) + 0.5
    nb = neighbourhoods(means, 16)
    assert nb.shape == (700, 16) and torch.equal(nb[:, 0], torch.arange(700))
    got = knn_pool(num, den, nb)
    ref = _old_knn_pool(means, num, den, 16)
    # the same 16 rows per Gaussian, summed in a possibly different order
    torch.testing.assert_close(got[0], ref[0], rtol=1e-6, atol=0)
    torch.testing.assert_close(got[1], ref[1], rtol=1e-6, atol=0)
    assert neighbourhoods(means[:3], 16).shape == (3, 3)
    assert torch.equal(neighbourhoods(means, 1), torch.arange(700)[:, None])


def test_expand_selection_matches_brute_force():
    g = torch.Generator().manual_seed(3)
    means = torch.rand(2000, 3, generator=g)
    selected = means[:, 0] < 0.2
    out = expand_selection(means, selected, 0.1)
    ref = selected | (_sq_dists(means, means[selected]) <= 0.01).any(1)
    assert torch.equal(out, ref) and (out & ~selected).any()


def test_quantile_box_is_not_stretched_by_a_stray_point():
    """The depth-initialization radius and the splat truths' object frame come from this box: one
    stray point (a floater, a stray selected Gaussian) must not set it, as it sets the min-max box."""
    pts = torch.rand(1000, 3, generator=torch.Generator().manual_seed(0))
    stray = torch.cat([pts, torch.tensor([[50.0, -50.0, 50.0]])])
    lo, hi = quantile_box(stray, 0.02)
    assert torch.all(lo > 0.0) and torch.all(lo < 0.05) and torch.all(hi < 1.0) and torch.all(hi > 0.95)
    assert torch.equal(torch.stack(quantile_box(stray, 0.0)), torch.stack([stray.min(0).values, stray.max(0).values]))


def _brute_components(neighbourhood, member):
    """Each member's smallest reachable member row by breadth-first search (the reference)."""
    n = member.shape[0]
    adjacent = [set() for _ in range(n)]
    for i in range(n):
        for j in neighbourhood[i].tolist():
            if member[i] and member[j]:
                adjacent[i].add(j)
                adjacent[j].add(i)
    label = [-1] * n
    for start in range(n):
        if member[start] and label[start] < 0:
            piece, todo = {start}, [start]
            while todo:
                for j in adjacent[todo.pop()]:
                    if j not in piece:
                        piece.add(j)
                        todo.append(j)
            for i in piece:
                label[i] = min(piece)
    return torch.tensor(label)


@pytest.mark.parametrize("name", ["uniform", "clustered", "duplicates", "few_points"])
@pytest.mark.parametrize("share", [0.2, 0.5, 1.0])
def test_components_equal_breadth_first_search(name, share):
    """The selection's connected pieces over a kNN graph (an edge either way round) equal a
    breadth-first search's, labelled by their smallest row, non-members -1."""
    points = _clouds()[name]
    member = torch.rand(points.shape[0], generator=torch.Generator().manual_seed(1)) < share
    neighbourhood = knn(points, 4)[1]
    assert torch.equal(components(neighbourhood, member), _brute_components(neighbourhood, member))


def test_components_of_a_chain_join_it_end_to_end():
    """A chain whose rows are shuffled (each joined to the next only, one way round) is one piece,
    however long; cut in the middle, two."""
    order = torch.randperm(3000, generator=torch.Generator().manual_seed(2))
    neighbourhood = torch.empty(3000, 1, dtype=torch.long)
    neighbourhood[order[:-1], 0] = order[1:]
    neighbourhood[order[-1], 0] = order[-1]
    member = torch.ones(3000, dtype=torch.bool)
    assert torch.equal(components(neighbourhood, member), torch.zeros(3000, dtype=torch.long))
    member[order[1500]] = False
    label = components(neighbourhood, member)
    assert label[order[1500]] == -1 and len(label[member].unique()) == 2
    assert (label[order[:1500]] == int(order[:1500].min())).all()
