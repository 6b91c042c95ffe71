"""The threestudio-style framework pieces: registry, strict configs, schedules, the image/video
helpers, BaseSystem's outputs and checkpoint extras, and the example plugin in custom/."""
import os
import random
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from trial_helpers import ROOT
from gs_regional.config import ConfigError, load_config, parse_structured, scheduled
from gs_regional.registry import RegistryError, find, note_import_error, register
from gs_regional.systems.base import BaseSystem, capture_rng_state, restore_rng_state
from gs_regional.utils import visualize



# ----- registry ------------------------------------------------------------------------------
def test_duplicate_name_names_both_classes():
    @register("test-dup-component")
    class First:
        pass

    with pytest.raises(RegistryError) as e:

        @register("test-dup-component")
        class Second:
            pass

    msg = str(e.value)
    assert "test_framework" in msg and "First" in msg and "Second" in msg
    assert find("test-dup-component") is First


def test_same_class_defined_again_by_the_same_module_replaces_itself():
    def define():
        @register("test-redefined-component")
        class Again:
            pass

        return Again

    a, b = define(), define()
    assert a is not b and find("test-redefined-component") is b


def test_unknown_name_lists_registered_names_of_its_kind():
    with pytest.raises(RegistryError) as e:
        find("no-such-editor", kind="guidance")
    msg = str(e.value)
    assert "unknown guidance type 'no-such-editor'" in msg
    assert "instructpix2pix" in msg  # a registered guidance
    assert "gaussian-model" not in msg  # a geometry is not listed for a guidance


def test_simulators_are_listed_with_the_interface_they_implement():
    """gs_regional/sim holds simulators of several kinds; an unknown-name error lists each among its peers."""
    with pytest.raises(RegistryError) as e:
        find("no-such-editor", kind="guidance")
    assert "simulated-editor" in str(e.value) and "synthetic-scene" not in str(e.value)
    with pytest.raises(RegistryError) as e:
        find("no-such-data", kind="data")
    assert "synthetic-scene" in str(e.value) and "simulated-depth" not in str(e.value)


def _runtime_imports(path: Path):
    """Modules a file imports when it runs (imports under `if TYPE_CHECKING:` are for annotations only)."""
    import ast

    tree = ast.parse(path.read_text())
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names)


# The floors of the package (docs/architecture.md): a module imports only from its own package
# and from lower floors, so each floor can be read, tested and replaced without the ones above.
FLOORS = {
    "config": 0, "registry": 1, "utils": 1,
    "data": 2, "geometry": 2,
    "renderers": 3,
    "guidance": 4, "depth": 4, "metrics": 4,
    "sim": 5,
    "stages": 6,
    "systems": 7,
    "launch": 8,
    "api": 9,  # the edit from Python runs launch's path
    "testing": 9,  # random-weight model folders for tests and benchmarks
    "studio": 10,  # the browser studio: runs the API (localize, edit) behind a viser page
    "bench": 10,  # benchmarks, the truth suite and the GPU checks: shared by scripts/ and the tests
}


def test_each_floor_imports_only_from_below():
    offenders = []
    for path in sorted((ROOT / "gs_regional").rglob("*.py")):
        rel = path.relative_to(ROOT / "gs_regional").with_suffix("")
        own = rel.parts[0]
        if own == "__init__":
            continue
        assert own in FLOORS, f"gs_regional/{own} has no floor in FLOORS (and docs/architecture.md)"
        for module in _runtime_imports(path):
            parts = module.split(".")
            if parts[0] != "gs_regional" or len(parts) < 2 or parts[1] == own:
                continue
            if FLOORS[parts[1]] >= FLOORS[own]:
                offenders.append(f"gs_regional/{rel}.py (floor {FLOORS[own]}) imports {module} (floor {FLOORS[parts[1]]})")
    assert not offenders, "\n".join(offenders)


def _top_level_imports(body):
    """The import statements a module runs when it is imported: its top level, including under
    `if`/`try`/`with` (not inside functions or classes, nor under `if TYPE_CHECKING:`)."""
    import ast

    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            if "TYPE_CHECKING" not in ast.unparse(node.test):
                yield from _top_level_imports(node.body)
            yield from _top_level_imports(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                yield from _top_level_imports(block)
        elif isinstance(node, ast.With):
            yield from _top_level_imports(node.body)


def import_graph(top_level_only=True):
    """{module: {imported gs_regional module: line}} of every module of gs_regional, from its source
    (`from pkg import name` is an edge to `pkg.name` when that is a module, else to `pkg`)."""
    import ast

    modules = {}
    for path in sorted((ROOT / "gs_regional").rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        is_package = parts[-1] == "__init__"
        modules[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    graph = {}
    for name, (path, is_package) in modules.items():
        tree = ast.parse(path.read_text())
        nodes = _top_level_imports(tree.body) if top_level_only else (
            n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)))
        package = name if is_package else name.rpartition(".")[0]
        edges = graph[name] = {}
        for node in nodes:
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the package, up level - 1
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(up + ([node.module] if node.module else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for target in targets:
                if target in modules and target != name:
                    edges.setdefault(target, node.lineno)
    return graph


def find_cycle(graph):
    """One import cycle of `graph` as [a, b, ..., a], or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in graph.get(node, ()):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def _describe_cycle(graph, cycle):
    return " -> ".join(cycle) + "  (" + "; ".join(
        f"{a} imports {b} at line {graph[a][b]}" for a, b in zip(cycle, cycle[1:])) + ")"


def test_find_cycle_names_the_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}, "d": {"a": 4}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b": 1}, "b": {}}) is None


def test_no_import_cycles_in_the_package():
    """Module-level imports of gs_regional form no cycle (a cycle makes a module's import depend
    on which module of the cycle was imported first)."""
    graph = import_graph(top_level_only=True)
    assert "gs_regional.launch.modes" in graph["gs_regional.launch.run"]  # the graph sees imports at all
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + _describe_cycle(graph, cycle)


def test_launch_flows_one_way():
    """Inside gs_regional.launch not even the imports inside functions form a cycle: cli parses and
    imports run, run executes and never imports cli (what both need is in modes.py)."""
    graph = import_graph(top_level_only=False)
    launch = {m: {t: line for t, line in edges.items() if t.startswith("gs_regional.launch")}
              for m, edges in graph.items() if m.startswith("gs_regional.launch")}
    assert "gs_regional.launch.run" in launch["gs_regional.launch.cli"]
    assert "gs_regional.launch.cli" not in launch["gs_regional.launch.run"]
    cycle = find_cycle(launch)
    assert cycle is None, "import cycle in gs_regional.launch: " + _describe_cycle(launch, cycle)


def test_unknown_name_mentions_modules_that_failed_to_import():
    note_import_error("plugin custom/broken.py", "ModuleNotFoundError: No module named 'nope'")
    try:
        with pytest.raises(RegistryError, match=r"custom/broken\.py \(ModuleNotFoundError: No module named 'nope'\)"):
            find("from-the-broken-plugin")
    finally:
        note_import_error("plugin custom/broken.py", None)
    with pytest.raises(RegistryError) as e:
        find("from-the-broken-plugin")
    assert "failed to import" not in str(e.value)


# ----- strict configs ------------------------------------------------------------------------
@dataclass
class _Geometry:
    ply: str = ""
    sh_degree: int = 3


@dataclass
class _SystemConfig:
    geometry: _Geometry = field(default_factory=_Geometry)
    lr: float = 0.1
    extra: dict = field(default_factory=dict)


def test_misspelt_nested_key_names_the_full_key():
    with pytest.raises(ConfigError) as e:
        parse_structured(_SystemConfig, {"geometry": {"plyy": "a.ply"}}, where="system")
    msg = str(e.value)
    assert "'system.geometry.plyy'" in msg
    assert "did you mean 'ply'" in msg and "allowed keys: ply, sh_degree" in msg


def test_bad_value_names_the_key_in_one_line():
    with pytest.raises(ConfigError) as e:
        parse_structured(_SystemConfig, {"geometry": {"sh_degree": "three"}}, where="system")
    assert "'system.geometry.sh_degree'" in str(e.value) and "\n" not in str(e.value)


def test_parse_structured_fills_defaults_and_keeps_free_dicts():
    cfg = parse_structured(_SystemConfig, {"lr": 0.5, "extra": {"anything": 1}}, where="system")
    assert cfg.lr == 0.5 and cfg.geometry.sh_degree == 3 and cfg.extra["anything"] == 1
    with pytest.raises(ConfigError, match="must be a mapping"):
        parse_structured(_SystemConfig, 5, where="system")


def test_load_config_overrides_defaults_and_errors(tmp_path):
    path = tmp_path / "exp.yaml"
    path.write_text("name: exp\nseed: 3\nsystem:\n  seed: ${seed}\n  lr: 0.1\n")
    cfg = load_config(str(path), ["system.lr=0.5", "seed=7"])
    assert cfg.system.lr == 0.5 and cfg.system.seed == 7  # interpolation resolved after overrides
    assert cfg.exp_root_dir == "outputs" and cfg.trainer == {}  # ExperimentConfig defaults
    with pytest.raises(ConfigError, match=r"exp\.yaml: unknown config key 'nmae' \(did you mean 'name'\?\)"):
        load_config(str(path), ["nmae=x"])
    with pytest.raises(ConfigError, match="not of the form key=value"):
        load_config(str(path), ["seed"])
    with pytest.raises(ConfigError, match=r"config file not found: .*missing\.yaml"):
        load_config(str(tmp_path / "missing.yaml"))
    bad = tmp_path / "list.yaml"
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(str(bad))


def test_scheduled_values():
    assert scheduled(0.3, 100) == 0.3
    assert scheduled(np.float32(2.0), 5) == 2.0
    ramp = [100, 1.0, 0.0, 200]
    assert scheduled(ramp, 0) == 1.0 and scheduled(ramp, 150) == pytest.approx(0.5) and scheduled(ramp, 999) == 0.0
    steps = [[0, 750], [500, 500], [1000, 250]]
    assert [scheduled(steps, s) for s in (0, 499, 500, 1200)] == [750, 750, 500, 250]
    assert scheduled(OmegaConf.create({"v": steps}).v, 600) == 500  # YAML lists work too
    with pytest.raises(ConfigError):
        scheduled([1, 2, 3], 0)
    with pytest.raises(ConfigError):
        scheduled("fast", 0)


# ----- images, grids, videos -------------------------------------------------------------------
def test_to_uint8_accepts_the_usual_image_kinds():
    f = torch.tensor([[[0.0, 0.5, 1.0]]])
    assert visualize.to_uint8(f).tolist() == [[[0, 128, 255]]]
    assert visualize.to_uint8(np.array([[True, False]])).tolist() == [[[255] * 3, [0] * 3]]
    assert visualize.to_uint8(np.array([[2.0, np.nan]])).tolist() == [[[255] * 3, [0] * 3]]  # clipped, NaN -> 0
    assert visualize.to_uint8(np.zeros((2, 2, 1), np.uint8)).shape == (2, 2, 3)
    with pytest.raises(ValueError, match=r"\(H, W, 3\).*\(2, 2, 5\)"):
        visualize.to_uint8(np.zeros((2, 2, 5)))


def test_make_grid_tiles_with_margins_and_labels():
    a = torch.zeros(4, 6, 3)
    b = np.ones((3, 2, 3))
    grid = visualize.make_grid([[a, b], [b]], margin=2)
    # columns: max widths 6 and 2; rows: max heights 4 and 3
    assert grid.shape == (2 + 4 + 2 + 3 + 2, 2 + 6 + 2 + 2 + 2, 3)
    assert (grid[2:6, 2:8] == 0).all() and (grid[2:5, 10:12] == 255).all()
    assert (grid[0:2] == 255).all()  # margin
    labelled = visualize.make_grid([[a, a]], labels=[["before", None]], margin=2)
    strip = labelled[2 : 2 + visualize.LABEL_HEIGHT]
    assert labelled.shape == (2 + visualize.LABEL_HEIGHT + 4 + 2, 2 + 6 + 2 + 6 + 2, 3)
    assert (strip[:, 2:8] < 255).any()  # text drawn in the first caption
    assert (strip[:, 10:16] == 255).all()  # no caption for the second
    with pytest.raises(ValueError, match="same nesting"):
        visualize.make_grid([[a, a]], labels=["one", "two"])


def test_overlay_mask_tints_only_the_mask():
    img = torch.full((2, 2, 3), 0.5)
    mask = torch.tensor([[True, False], [False, False]])
    out = visualize.overlay_mask(img, mask, color=(1, 0, 0), alpha=0.5)
    assert isinstance(out, torch.Tensor) and out.shape == (2, 2, 3)
    assert torch.allclose(out[0, 0], torch.tensor([0.75, 0.25, 0.25]))
    assert torch.equal(out[1], img[1])
    with pytest.raises(ValueError, match="mask must be"):
        visualize.overlay_mask(img, torch.ones(3, 3))


def test_save_image_is_atomic_and_readable(tmp_path):
    import imageio.v3 as iio

    img = torch.rand(5, 7, 3)
    path = visualize.save_image(tmp_path / "sub" / "x.png", img)
    back = iio.imread(path)
    assert back.shape == (5, 7, 3) and np.array_equal(back, visualize.to_uint8(img))
    with pytest.raises(ValueError):
        visualize.save_image(path, np.zeros((5, 7, 9)))  # bad image: the old file is untouched
    assert np.array_equal(iio.imread(path), back)
    assert sorted(os.listdir(tmp_path / "sub")) == ["x.png"]  # no temporary files left


def _frames(n=7, h=17, w=22):
    return [torch.full((h, w, 3), i / n) for i in range(n)]


def test_save_video_writes_an_mp4_imageio_reads_back(tmp_path):
    import imageio.v3 as iio

    path = visualize.save_video(tmp_path / "turntable.mp4", _frames(), fps=10)
    assert path.endswith(".mp4")
    frames = iio.imread(path)
    assert frames.shape[0] == 7 and frames.shape[1:3] == (18, 22)  # odd height padded for H.264
    assert abs(int(frames[3].mean()) - round(3 / 7 * 255)) <= 3
    assert os.listdir(tmp_path) == ["turntable.mp4"]


def test_save_video_falls_back_to_gif_when_ffmpeg_fails(tmp_path, monkeypatch):
    import imageio.v3 as iio

    def no_ffmpeg(*a, **k):
        raise RuntimeError("no ffmpeg here")

    monkeypatch.setattr(visualize, "_write_mp4", no_ffmpeg)
    with pytest.warns(RuntimeWarning, match="ffmpeg is unavailable.*no ffmpeg here"):
        path = visualize.save_video(tmp_path / "turntable.mp4", _frames(5), fps=10)
    assert path.endswith("turntable.gif")
    assert iio.imread(path, index=None).shape[0] == 5
    assert os.listdir(tmp_path) == ["turntable.gif"]
    with pytest.raises(ValueError, match="same size"):
        visualize.save_video(tmp_path / "v.mp4", [torch.zeros(4, 4, 3), torch.zeros(4, 6, 3)])


# ----- BaseSystem ----------------------------------------------------------------------------
@dataclass
class _Inner:
    size: int = 2


class _System(BaseSystem):
    @dataclass
    class Config:
        inner: _Inner = field(default_factory=_Inner)
        max_steps: int = 12

    def __init__(self, cfg=None, resumed=False):
        super().__init__(cfg, resumed=resumed)
        self.counter = 0

    def extra_state(self):
        return {"counter": self.counter, "buffer": torch.arange(3)}

    def load_extra_state(self, state):
        self.counter = state["counter"]


def test_base_system_config_stage_and_outputs(tmp_path):
    with pytest.raises(ConfigError, match="'system.inner.sise'"):
        _System({"inner": {"sise": 3}})
    s = _System({"inner": {"size": 4}})
    assert s.cfg.inner.size == 4 and s.automatic_optimization is False and s.total_steps == 12
    with pytest.raises(RuntimeError, match="set_trial_dir"):
        s.save_dir
    s.set_trial_dir(tmp_path)
    s.set_stage("refine cycle 2/3")
    assert s.stage == "refine cycle 2/3"
    p = s.save_image("views/a.png", torch.rand(4, 5, 3))
    assert Path(p) == tmp_path / "save" / "views" / "a.png" and Path(p).is_file()
    assert Path(s.save_image_grid("grid.png", [[torch.rand(4, 5, 3)] * 2])).is_file()
    assert Path(s.save_video("v.mp4", _frames(3))).is_file()
    with pytest.raises(ValueError, match="inside the save directory"):
        s.save_image("../escape.png", torch.rand(2, 2, 3))
    s.log_metrics({"loss": 1.0})  # no trainer: nothing to log to, and no error
    s.write_metrics_json({"a": 1, "t": torch.tensor(2.5)})
    s.write_metrics_json({"b": [1, 2]})
    import json

    assert json.loads((tmp_path / "save" / "metrics.json").read_text()) == {"a": 1, "t": 2.5, "b": [1, 2]}
    s.write_metrics_json({"c": 3}, merge=False)
    assert json.loads((tmp_path / "save" / "metrics.json").read_text()) == {"c": 3}


def test_checkpoint_extras_restore_rng_stage_and_state(tmp_path):
    s = _System()
    s.set_stage("localize")
    s.counter = 5
    ckpt = {}
    s.on_save_checkpoint(ckpt)
    expected = (torch.rand(3), np.random.rand(3), random.random())
    # The checkpoint must load with torch's safe loader (weights_only=True).
    torch.save(ckpt, tmp_path / "c.pt")
    loaded = torch.load(tmp_path / "c.pt", weights_only=True)
    torch.manual_seed(123), np.random.seed(123), random.seed(123)
    t = _System()
    t.on_load_checkpoint(loaded)
    assert t.stage == "localize" and t.counter == 5
    t.on_train_batch_start(None, 0)  # a state saved mid-epoch is restored before the next step
    again = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(expected[0], again[0]) and np.array_equal(expected[1], again[1]) and expected[2] == again[2]
    assert "trial" not in repr(ckpt) and str(tmp_path) not in repr(ckpt)  # no paths in checkpoints


def test_rng_state_roundtrip():
    state = capture_rng_state()
    a = (torch.randn(4), np.random.randn(4), random.random())
    restore_rng_state(state)
    b = (torch.randn(4), np.random.randn(4), random.random())
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]


# ----- the example plugin --------------------------------------------------------------------
def test_example_plugin_loads_and_desaturates_the_colourful_region():
    from gs_regional.launch import load_plugins

    results = load_plugins(ROOT / "custom")
    assert results.get("custom/example_plugin.py", "missing") is None, results
    editor = find("grayscale-editor", kind="guidance")({"strength": 1.0})
    img = torch.full((1, 16, 16, 3), 0.5)
    img[0, 4:10, 4:10] = torch.tensor([0.9, 0.1, 0.1])  # a red square on grey
    rel = editor.relevance(img, "make it black and white")
    assert rel.shape == (1, 16, 16) and rel[0, 5, 5] == 1.0 and rel[0, 0, 0] == 0.0
    mask = editor.mask(img, "make it black and white", threshold=0.6, blur_sigma=0.5)
    assert mask[0, 4:10, 4:10].all() and mask.sum() == 36
    out = editor.edit(img, img, "make it black and white")
    assert torch.allclose(out[..., 0], out[..., 1]) and torch.allclose(out[..., 1], out[..., 2])
    luma = 0.299 * 0.9 + 0.587 * 0.1 + 0.114 * 0.1
    assert out[0, 5, 5, 0] == pytest.approx(luma) and out[0, 0, 0, 0] == pytest.approx(0.5)
    half = editor.edit(img, img, "make it black and white", t_start=500)  # lower t: a milder edit
    assert half[0, 5, 5, 0] == pytest.approx((0.9 + luma) / 2)
    assert editor.counters()["unet_evals"] == 0
    with pytest.raises(ConfigError, match="strength"):
        find("grayscale-editor")({"strength": 2.0})
