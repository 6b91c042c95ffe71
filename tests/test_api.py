"""The small public API users and scripts rely on (README "Python API")."""
import torch
from plyfile import PlyData

import gs_regional as gr
from trial_helpers import shared_path


def test_load_render_save_a_real_splat_with_real_cameras(tmp_path):
    """donut.ply (a trained 3DGS) rendered from cameras loaded through load_cameras."""
    from gs_regional.data.loaders import save_cameras_json
    from gs_regional.sim.scene import look_at

    model = gr.GaussianModel.from_ply(str(shared_path("donut", "donut.ply")))
    center = model.means.detach().median(0).values
    extent = float((model.means.detach() - center).norm(dim=-1).quantile(0.9))
    cams = [look_at(center + torch.tensor([0.0, -0.5, -2.5]) * extent, center, 48, 40, name=f"v{i}") for i in range(1)]
    save_cameras_json(cams, str(tmp_path / "cameras.json"))
    loaded = gr.load_cameras(str(tmp_path))
    assert len(loaded) == 1 and (loaded[0].width, loaded[0].height) == (48, 40)
    with torch.no_grad():
        out = gr.render(model, loaded[0], background=(1.0, 1.0, 1.0))
    assert out["rgb"].shape == (40, 48, 3) and out["depth"].shape == (40, 48) and out["alpha"].shape == (40, 48)
    # The donut is in view (opaque over a good part of the image; its hole may be at the centre),
    # and the background is white where nothing is.
    assert float(out["alpha"].max()) > 0.9 and float((out["alpha"] > 0.5).float().mean()) > 0.05
    bg = out["alpha"] < 1e-3
    if bool(bg.any()):
        assert torch.allclose(out["rgb"][bg], torch.ones_like(out["rgb"][bg]), atol=1e-4)
    dst = tmp_path / "copy.ply"
    model.save_ply(str(dst))
    assert PlyData.read(str(dst))["vertex"].count == model.num_gaussians


def test_registered_components_are_listed_by_name():
    names = set(gr.registered())
    for name in ["gaussian-model", "torch-rasterizer", "gsplat-rasterizer", "instructpix2pix", "simulated-editor",
                 "depth-anything", "simulated-depth", "scene-datamodule", "synthetic-scene",
                 "regional-edit", "in2n", "reconstruct"]:
        assert name in names, name
    assert gr.find("regional-edit").__name__ == "RegionalEdit"
