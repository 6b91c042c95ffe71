"""INRIA PLY reading/writing, bad-input errors, atomic writes and input protection."""
import json
import os

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from trial_helpers import shared_path
from gs_regional.geometry import ply as plymod
from gs_regional.geometry.gaussian_model import GaussianModel
from gs_regional.geometry.ply import PlyError, read_ply, standard_property_names, write_ply
from gs_regional.utils.io import OverwriteError, atomic_write, check_not_overwriting, write_json_atomic


def _bits(a):
    return np.ascontiguousarray(a).view(np.uint32)


def _write_with_plyfile(path, columns, text=False):
    """Write a vertex element whose properties are `columns` (name -> array), in that order."""
    n = len(next(iter(columns.values())))
    rows = np.empty(n, dtype=[(k, np.asarray(v).dtype.str) for k, v in columns.items()])
    for k, v in columns.items():
        rows[k] = v
    PlyData([PlyElement.describe(rows, "vertex")], text=text).write(str(path))


def _scene_columns(n, degree, seed=0):
    rng = np.random.default_rng(seed)
    cols = {}
    for name in standard_property_names(degree):
        cols[name] = rng.standard_normal(n).astype(np.float32)
    return cols


def test_donut_round_trip_is_bit_exact(tmp_path):
    src = shared_path("donut", "donut.ply")
    model = GaussianModel.from_ply(src)
    assert model.num_gaussians == 45624 and model.sh_degree == 0
    assert model.sh_rest.shape == (45624, 0, 3)
    out = tmp_path / "out" / "donut_copy.ply"  # parent folder is created
    model.save_ply(out)

    a = PlyData.read(str(src))["vertex"].data
    b_ply = PlyData.read(str(out))
    assert b_ply.byte_order == "<" and not b_ply.text
    b = b_ply["vertex"].data
    # Exact INRIA layout; the source's properties appear in the same relative order.
    assert list(b.dtype.names) == standard_property_names(0)
    assert [p for p in b.dtype.names if p in a.dtype.names] == list(a.dtype.names)
    for name in a.dtype.names:
        assert b.dtype[name] == np.dtype("<f4")
        assert np.array_equal(_bits(a[name]), _bits(b[name])), name
    for name in ("nx", "ny", "nz"):  # absent in the source: written as zeros
        assert not b[name].any()


def test_degree3_file_written_by_plyfile(tmp_path):
    n = 6
    cols = _scene_columns(n, 3)
    # f_rest_i of Gaussian g holds 1000*g + i so the channel-major mapping is checkable.
    for i in range(45):
        cols[f"f_rest_{i}"] = (1000 * np.arange(n) + i).astype(np.float32)
    cols["nx"] = np.linspace(-1, 1, n).astype(np.float32)
    cols["label"] = np.arange(n, dtype=np.int32) * 7 - 3
    cols["red"] = np.array([0, 1, 2, 253, 254, 255], dtype=np.uint8)
    path = tmp_path / "deg3.ply"
    _write_with_plyfile(path, cols)

    m = GaussianModel.from_ply(path)
    assert m.sh_degree == 3 and m.sh_rest.shape == (n, 15, 3)
    for g in range(n):
        for c in range(3):
            for k in range(15):
                assert m.sh_rest[g, k, c].item() == 1000 * g + c * 15 + k
    assert torch.equal(m.means[:, 1], torch.from_numpy(cols["y"]))
    assert torch.equal(m.quats[:, 0], torch.from_numpy(cols["rot_0"]))  # w first
    assert torch.equal(m.opacity_logits.detach(), torch.from_numpy(cols["opacity"]))
    assert torch.equal(m.log_scales[:, 2], torch.from_numpy(cols["scale_2"]))
    assert m.extra_names == ["label", "red", "nx", "ny", "nz"]  # non-zero normals are kept too

    out = tmp_path / "deg3_out.ply"
    m.save_ply(out)
    b = PlyData.read(str(out))["vertex"].data
    assert list(b.dtype.names) == standard_property_names(3) + ["label", "red"]
    assert b.dtype["label"] == np.dtype("<i4") and b.dtype["red"] == np.dtype("u1")
    for name, v in cols.items():
        assert np.array_equal(b[name], v), name


def test_property_order_and_text_format_do_not_matter(tmp_path):
    cols = _scene_columns(5, 1, seed=3)
    shuffled = {k: cols[k] for k in reversed(list(cols))}
    _write_with_plyfile(tmp_path / "a.ply", cols)
    _write_with_plyfile(tmp_path / "b.ply", shuffled, text=True)
    a, b = read_ply(tmp_path / "a.ply"), read_ply(tmp_path / "b.ply")
    assert a.sh_degree == 1
    for field in ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats"):
        np.testing.assert_allclose(getattr(a, field), getattr(b, field), rtol=1e-6)


def _expect(path, *fragments, **kw):
    with pytest.raises(PlyError) as e:
        read_ply(path, **kw)
    msg = str(e.value)
    assert str(path) in msg, msg
    for f in fragments:
        assert f in msg, msg
    return msg


def test_bad_inputs_raise_plyerror_naming_file_and_problem(tmp_path):
    _expect(tmp_path / "nope.ply", "not found")

    (tmp_path / "empty.ply").write_bytes(b"")
    _expect(tmp_path / "empty.ply", "empty file")

    (tmp_path / "notes.txt").write_text("these are not the Gaussians you are looking for\n")
    _expect(tmp_path / "notes.txt", "not a PLY")

    cols = _scene_columns(4, 0)
    del cols["rot_3"], cols["scale_1"]
    _write_with_plyfile(tmp_path / "missing.ply", cols)
    _expect(tmp_path / "missing.ply", "missing vertex properties", "scale_1", "rot_3")

    cols = _scene_columns(4, 0)
    cols.update({f"f_rest_{i}": np.zeros(4, np.float32) for i in range(10)})
    _write_with_plyfile(tmp_path / "rest10.ply", cols)
    _expect(tmp_path / "rest10.ply", "10 f_rest", "0, 9, 24 or 45")

    _write_with_plyfile(tmp_path / "zero.ply", _scene_columns(0, 0))
    _expect(tmp_path / "zero.ply", "0 vertices")

    faces = np.empty(1, dtype=[("a", "i4")])
    PlyData([PlyElement.describe(faces, "face")]).write(str(tmp_path / "novertex.ply"))
    _expect(tmp_path / "novertex.ply", "no 'vertex' element", "face")

    _write_with_plyfile(tmp_path / "full.ply", _scene_columns(50, 0))
    data = (tmp_path / "full.ply").read_bytes()
    (tmp_path / "truncated.ply").write_bytes(data[: len(data) - 100])
    _expect(tmp_path / "truncated.ply", "cannot parse PLY")


def test_nonfinite_values_are_reported_or_dropped(tmp_path):
    cols = _scene_columns(10, 0)
    cols["x"][2] = np.nan
    cols["opacity"][2] = np.inf
    cols["rot_1"][7] = -np.inf
    path = tmp_path / "nan.ply"
    _write_with_plyfile(path, cols)
    msg = _expect(path, "2 of 10 Gaussians", "3 values", "x", "opacity", "rot_1", "drop_nonfinite")
    assert "scale_0" not in msg

    with pytest.warns(UserWarning, match="2 of 10 Gaussians"):
        m = GaussianModel.from_ply(path, drop_nonfinite=True)
    assert m.num_gaussians == 8
    keep = np.array([i not in (2, 7) for i in range(10)])
    assert torch.equal(m.means[:, 1], torch.from_numpy(cols["y"][keep]))
    # the config flag reaches the reader too
    with pytest.warns(UserWarning, match="dropping"):
        assert len(GaussianModel({"ply": str(path), "drop_nonfinite": True})) == 8


def test_atomic_write_removes_temp_on_failure_and_keeps_old_file(tmp_path):
    target = tmp_path / "sub" / "x.txt"
    with atomic_write(target) as tmp:
        assert os.path.dirname(tmp) == str(target.parent)
        with open(tmp, "w") as f:
            f.write("old")
    assert target.read_text() == "old"
    with pytest.raises(RuntimeError):
        with atomic_write(target) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise RuntimeError("disk on fire")
    assert target.read_text() == "old"
    assert os.listdir(target.parent) == ["x.txt"]


def test_write_ply_failure_leaves_no_partial_file(tmp_path, monkeypatch):
    m = GaussianModel.from_tensors(torch.zeros(3, 3), torch.tensor([[1.0, 0, 0, 0]] * 3), torch.zeros(3, 3),
                                   torch.zeros(3), torch.zeros(3, 3))
    out = tmp_path / "scene.ply"

    def broken_write(self, stream):
        with open(stream, "wb") as f:
            f.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("no space left on device")

    monkeypatch.setattr(PlyData, "write", broken_write)
    with pytest.raises(OSError, match="no space"):
        m.save_ply(out)
    assert os.listdir(tmp_path) == []


def test_save_refuses_to_overwrite_the_source(tmp_path):
    src = tmp_path / "scene.ply"
    _write_with_plyfile(src, _scene_columns(5, 0))
    before = src.read_bytes()
    m = GaussianModel.from_ply(src)
    with pytest.raises(OverwriteError, match="input file"):
        m.save_ply(src)
    os.symlink(src, tmp_path / "link.ply")
    with pytest.raises(OverwriteError):
        m.save_ply(tmp_path / "link.ply")
    os.link(src, tmp_path / "hard.ply")
    with pytest.raises(OverwriteError):
        m.save_ply(tmp_path / "hard.ply")
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        with pytest.raises(OverwriteError):
            m.save_ply("scene.ply")
    finally:
        os.chdir(cwd)
    assert src.read_bytes() == before
    m.save_ply(tmp_path / "other.ply")  # any other path is fine
    check_not_overwriting(tmp_path / "other.ply", [None, src])


def test_write_json_atomic_converts_numbers(tmp_path):
    path = tmp_path / "m" / "metrics.json"
    write_json_atomic(path, {"n": np.int64(3), "psnr": torch.tensor(31.5), "v": np.arange(2), "p": tmp_path})
    assert json.loads(path.read_text()) == {"n": 3, "psnr": 31.5, "v": [0, 1], "p": str(tmp_path)}
    assert os.listdir(path.parent) == ["metrics.json"]


def test_write_ply_rejects_inconsistent_arrays(tmp_path):
    g = read_ply(_write_tmp_scene(tmp_path))
    g.log_scales = g.log_scales[:2]
    with pytest.raises(PlyError, match="log_scales"):
        write_ply(tmp_path / "bad.ply", g)
    assert not (tmp_path / "bad.ply").exists()


def _write_tmp_scene(tmp_path):
    path = tmp_path / "s.ply"
    _write_with_plyfile(path, _scene_columns(4, 2))
    return path


def test_plyerror_is_valueerror():
    assert issubclass(plymod.PlyError, ValueError)


def test_big_endian_and_mixed_type_files_read_like_little_endian_float32(tmp_path):
    # All-float32 files take the vectorised (N, P) path; big-endian ones are converted first, and
    # an integer extra sends the file down the per-property path: all three must agree bit for bit.
    cols = _scene_columns(7, 3, seed=5)
    cols["x"][3] = np.nan  # the non-finite handling runs on every path
    _write_with_plyfile(tmp_path / "le.ply", cols)
    rows = np.empty(7, dtype=[(k, ">f4") for k in cols])
    for k, v in cols.items():
        rows[k] = v
    PlyData([PlyElement.describe(rows, "vertex")], byte_order=">").write(str(tmp_path / "be.ply"))
    _write_with_plyfile(tmp_path / "mixed.ply", {**cols, "label": np.arange(7, dtype=np.int16)})
    with pytest.warns(UserWarning, match="1 of 7"):
        ref = read_ply(tmp_path / "le.ply", drop_nonfinite=True)
    for name in ("be.ply", "mixed.ply"):
        with pytest.warns(UserWarning, match="1 of 7"):
            got = read_ply(tmp_path / name, drop_nonfinite=True)
        for field in ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats", "normals"):
            a, b = getattr(ref, field), getattr(got, field)
            assert a.dtype == b.dtype == np.float32 and np.array_equal(_bits(a), _bits(b)), (name, field)
    assert list(got.extras) == ["label"] and got.extras["label"].tolist() == [0, 1, 2, 4, 5, 6]


def test_read_arrays_do_not_alias_the_file(tmp_path):
    # The vertex block is memory-mapped while reading: what read_ply returns must be copies, or
    # a later change of the file on disk would show through.
    path = tmp_path / "s.ply"
    _write_with_plyfile(path, _scene_columns(5, 1))
    g = read_ply(path)
    before = {f: getattr(g, f).copy() for f in ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")}
    data = bytearray(path.read_bytes())
    header_end = data.index(b"end_header\n") + len(b"end_header\n")
    data[header_end:] = bytes(len(data) - header_end)
    with open(path, "r+b") as f:  # in place: the same inode the mapping was made from
        f.write(data)
    for f, v in before.items():
        assert np.array_equal(getattr(g, f), v), f


@pytest.mark.parametrize("degree", [0, 3])
def test_ply_bytes_with_rows_is_the_size_write_ply_gives(tmp_path, degree):
    """The size of a PLY with another number of rows, predicted from a written one's header
    (extras of other types included), equals the size of actually writing it."""
    cols = _scene_columns(1000, degree)
    cols["label"] = np.arange(1000, dtype=np.int16)
    _write_with_plyfile(tmp_path / "full.ply", cols)
    full = read_ply(tmp_path / "full.ply")
    write_ply(tmp_path / "rewritten.ply", full)
    for rows in (7, 0):
        part = {f: getattr(full, f)[:rows] for f in ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")}
        normals = None if full.normals is None else full.normals[:rows]
        extras = {k: v[:rows] for k, v in full.extras.items()}
        write_ply(tmp_path / "part.ply", plymod.PlyGaussians(**part, normals=normals, extras=extras))
        assert plymod.ply_bytes_with_rows(tmp_path / "part.ply", 1000) == os.path.getsize(tmp_path / "rewritten.ply")
        assert plymod.ply_bytes_with_rows(tmp_path / "rewritten.ply", rows) == os.path.getsize(tmp_path / "part.ply")
    _write_with_plyfile(tmp_path / "text.ply", cols, text=True)
    with pytest.raises(PlyError, match="binary"):
        plymod.ply_bytes_with_rows(tmp_path / "text.ply", 5)
