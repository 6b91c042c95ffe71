"""Data-parallel editing (gs_regional/systems/parallel.py): `trainer.accelerator=cpu
trainer.devices=2` runs the demo on two processes of Lightning's launcher over gloo and gives the
same edit as one process, with one set of outputs, and resumes on the same or another number of
processes; the split of the views, the launch settings and the errors of bad use, without
processes."""
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from trial_helpers import launch, launch_process, metrics_of as metrics, trial_of
from gs_regional.config import ConfigError
from gs_regional.launch.run import data_parallel_kwargs
from gs_regional.systems import parallel

# Every run is the small demo (tests/data/small_demo.yaml): 3 cycles of 4 steps, densifying every
# 2 steps, 4 views per cycle (m=3 and the frontal view).
TWO = ["trainer.accelerator=cpu", "trainer.devices=2"]
# The two-process run checkpoints at steps 6 and 12: its last.ckpt.previous, in the second cycle
# after the first's densifications, is where the resume tests start from.
CHECKPOINTS = "checkpoint.every_n_train_steps=6"


# ----------------------------------------------------------------------------- without processes
def test_share_gives_every_item_to_one_process_in_turn():
    for n in range(0, 9):
        for world in range(1, 5):
            shares = [parallel.share(n, r, world) for r in range(world)]
            assert sorted(i for s in shares for i in s) == list(range(n))
            assert max(map(len, shares)) - min(map(len, shares)) <= 1
    assert parallel.share(7, 1, 3) == [1, 4]
    with pytest.raises(ValueError):
        parallel.share(4, 2, 2)


class _FakeStrategy:
    """all_gather of a world whose processes are simulated: every rank's padded share at once."""

    def __init__(self, per_rank):
        self.per_rank = per_rank

    def all_gather(self, tensor):
        return torch.stack(self.per_rank)


@pytest.mark.parametrize("n,world", [(5, 2), (7, 3), (2, 3), (4, 4)])
def test_gathered_shares_come_back_in_item_order(n, world):
    item = lambda i: torch.full((2, 3), float(i))  # noqa: E731 - the result of item i
    rows = -(-n // world)
    padded = []
    for r in range(world):
        mine = [item(i) for i in parallel.share(n, r, world)]
        mine += [torch.zeros(2, 3)] * (rows - len(mine))
        padded.append(torch.stack(mine))
    for rank in range(world):
        local = padded[rank][: len(parallel.share(n, rank, world))]
        module = SimpleNamespace(trainer=SimpleNamespace(global_rank=rank, world_size=world,
                                                         strategy=_FakeStrategy(padded)), device="cpu")
        out = parallel.gather_shares(module, local, n)
        assert torch.equal(out, torch.stack([item(i) for i in range(n)]))


def test_one_process_changes_nothing():
    module = SimpleNamespace(trainer=SimpleNamespace(global_rank=0, world_size=1), device="cpu")
    assert parallel.rank_and_world(module) == (0, 1) and parallel.is_rank_zero(module)
    x = torch.arange(6.0).view(3, 2)
    assert parallel.map_views(module, 3, lambda ks: x[ks], (2,)).equal(x)
    assert parallel.from_rank_zero(module, x) is x
    assert parallel.sum_increments(module, {"a": 1}, {"a": 5}) == {"a": 5}
    parallel.check_agree(module, "nothing", [1.0])


def test_processes_requested_by_the_trainer_settings():
    assert parallel.requested_processes({"accelerator": "cpu", "devices": 2}) == 2
    assert parallel.requested_processes({"accelerator": "cpu", "devices": "3"}) == 3
    assert parallel.requested_processes({"accelerator": "cpu"}) == 1
    with pytest.raises(ConfigError, match="devices"):
        parallel.requested_processes({"accelerator": "cpu", "devices": 0})
    if torch.cuda.device_count() < 2:
        with pytest.raises(ConfigError, match="GPU"):
            parallel.requested_processes({"accelerator": "gpu", "devices": [0, 1]})


def test_bad_use_of_several_processes_is_a_clear_error():
    one = SimpleNamespace(registered_name="in2n")  # a system that does not share its work
    kw = {"accelerator": "cpu", "devices": 2}
    assert data_parallel_kwargs({"accelerator": "cpu", "devices": 1}, one, "train", None) == {"accelerator": "cpu", "devices": 1}
    with pytest.raises(ConfigError, match="system 'in2n' runs on one process"):
        data_parallel_kwargs(kw, one, "train", None)
    edit = SimpleNamespace(registered_name="regional-edit", check_processes=lambda n, scene: None)
    with pytest.raises(ConfigError, match="--test runs on one process"):
        data_parallel_kwargs(kw, edit, "test", None)
    with pytest.raises(ConfigError, match="trainer.strategy='fsdp'"):
        data_parallel_kwargs({**kw, "strategy": "fsdp"}, edit, "train", None)
    out = data_parallel_kwargs(kw, edit, "train", None)
    assert isinstance(out["strategy"], parallel.EditDDPStrategy)
    with pytest.raises(ConfigError, match="--gpu 0,1 asks for 2 GPUs but CUDA is not available"):
        parallel.check_gpu_list([0, 1], False, 0)
    with pytest.raises(ConfigError, match="has 1 CUDA GPU.*no GPU 1"):
        parallel.check_gpu_list([0, 1], True, 1)
    parallel.check_gpu_list([0], False, 0)  # one GPU index without CUDA: the CPU, with a warning


def test_more_processes_than_views_is_refused_before_any_trial_dir(tmp_path, capsys):
    # 4 views per refinement cycle (m=3 and the frontal view) cannot be shared by 5 processes.
    launch(tmp_path, "many", "trainer.accelerator=cpu", "trainer.devices=5", expect=2)
    err = capsys.readouterr().err
    assert "ask for 5 processes, but the edit has only 4 views in each refinement cycle" in err
    assert "give at most 4 devices" in err
    assert not (tmp_path / "many").exists()


@pytest.mark.skipif(torch.cuda.device_count() >= 2, reason="this machine has the GPUs")
def test_a_gpu_list_this_machine_does_not_have_is_refused(tmp_path, capsys):
    launch(tmp_path, "gpus", args=("--gpu", "0,1"), expect=2)
    err = capsys.readouterr().err
    assert "--gpu 0,1" in err and "GPU" in err
    assert not (tmp_path / "gpus").exists()


def test_bench_parallel_reports_each_stage_against_one_process():
    from gs_regional.bench import parallel as bench_parallel

    def run(k, localize, edit):
        return {"processes": k, "wall_seconds": 10.0, "unet_evals": 489, "vae_encodes": 47, "vae_decodes": 18,
                "seconds": {"localize": localize, "refine_edit": edit, "refine_train": 1.0}}

    runs = {1: run(1, 4.0, 6.0), 2: run(2, 2.0, 4.0)}
    up = bench_parallel.speedups(runs)
    assert up[1]["localize"] == 1.0 and up[2]["localize"] == 2.0 and up[2]["refine_edit"] == 1.5
    assert up[2]["diffusion"] == 1.667
    report = {"device": {"name": "cpu"}, "models": "tiny", "dtype": "float32", "same_work": True,
              "budget": {"resolution": 64, "max_views": 12, "m": 8, "cycles": 2}, "runs": {str(k): v for k, v in runs.items()},
              "speedup": {str(k): v for k, v in up.items()}}
    text = bench_parallel.table(report)
    assert "2.00x" in text and "1.50x" in text and "warning" not in text
    args = bench_parallel.parse_args(["--models", "tiny", "--out", "x", "--device", "cpu"])
    assert args.processes == [1, 2] and args.max_views == 12


# ----------------------------------------------------------------------------- two processes
def launch_two(out, name, *overrides):
    """The small demo on several processes: launch.py in a fresh process (Lightning's launcher runs
    launch.py again for rank 1: never from inside pytest); returns (trial dir, stdout)."""
    stdout = launch_process(out, name, *overrides).stdout.decode()
    return trial_of(out, name), stdout


@pytest.fixture(scope="module")
def runs(tmp_path_factory, small_demo_run):
    """The small demo on one process (the session's run) and on two."""
    out = tmp_path_factory.mktemp("parallel")
    two, stdout = launch_two(out, "two", *TWO, CHECKPOINTS)
    return {"out": out, "one": small_demo_run, "two": two, "two_stdout": stdout}


def assert_same_edit(m, ref):
    """The same edit: mask IoU within 0.02, footprint PSNR within 0.3 dB, Gaussians within 1 %,
    and the same work (counters summed over the processes)."""
    assert abs(m["mask_iou"] - ref["mask_iou"]) <= 0.02
    assert abs(m["psnr_region_vs_true_edit"] - ref["psnr_region_vs_true_edit"]) <= 0.3
    assert abs(m["gaussians_after"] - ref["gaussians_after"]) <= 0.01 * ref["gaussians_after"]
    for key in ("unet_evals", "vae_encodes", "vae_decodes", "gaussians_before", "count_selected", "v_first"):
        assert m[key] == ref[key], key


def test_two_processes_give_the_edit_of_one(runs):
    one, two = metrics(runs["one"]), metrics(runs["two"])
    assert (one["world_size"], two["world_size"]) == (1, 2)
    assert two["warnings"] == [] and "stopped" not in two
    assert_same_edit(two, one)
    # On the CPU the two processes reproduce one process's numbers: the same views per step, the
    # same split samples (rank 0's RNG), per-view seeds.
    assert two["gaussians_after"] == one["gaussians_after"]
    assert two["psnr_vs_true_edit"] == pytest.approx(one["psnr_vs_true_edit"], abs=1e-3)


def test_two_processes_write_one_set_of_outputs(runs):
    trial = Path(runs["two"])
    assert [p.name for p in trial.parent.iterdir()] == [trial.name]  # one trial dir
    assert len((trial / "cmd.txt").read_text().splitlines()) == 1
    assert sorted(p.name for p in (trial / "configs").iterdir()) == ["parsed.yaml", "raw.yaml"]
    assert sorted(p.name for p in (trial / "ckpts").iterdir()) == ["last.ckpt", "last.ckpt.previous"]
    assert [p.name for p in (trial / "csv_logs").rglob("*.csv")] == ["metrics.csv"]
    assert (trial / "save" / "edited.ply").is_file() and (trial / "save" / "turntable.mp4").is_file()
    stdout = runs["two_stdout"]
    assert stdout.count("results: ") == 1 and stdout.count("trial dir: ") <= 1  # rank 0 alone prints
    ckpt = torch.load(trial / "ckpts" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 12


@pytest.mark.parametrize("processes", [1, 2], ids=["resumed-on-1", "resumed-on-2"])
def test_a_two_process_run_resumes_on_any_number_of_processes(runs, processes, tmp_path):
    """The two-process run's checkpoint at step 6 of 12 (in the second cycle, after the first's
    densifications), resumed on 1 or 2 processes: the edit of the uninterrupted run."""
    trial = tmp_path / "stopped" / Path(runs["two"]).name
    shutil.copytree(runs["two"], trial)
    ckpt = trial / "ckpts" / "last.ckpt.previous"
    assert torch.load(ckpt, map_location="cpu", weights_only=True)["global_step"] == 6
    resume = f"resume={ckpt}"
    if processes == 2:
        resumed, _ = launch_two(tmp_path, "stopped", *TWO, CHECKPOINTS, resume)
    else:  # one process needs no launcher: in this process (a Python start-up fewer)
        resumed = launch(tmp_path, "stopped", CHECKPOINTS, resume)
    assert Path(resumed) == trial
    m = metrics(trial)
    assert m["world_size"] == processes
    assert_same_edit(m, metrics(runs["one"]))
    assert m["gaussians_after"] == metrics(runs["one"])["gaussians_after"]
