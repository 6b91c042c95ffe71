"""Data-parallel editing over the processes of Lightning's DDP launcher (`--gpu 0,1,2,3`,
`trainer.devices=N`; on a CPU-only machine `trainer.accelerator=cpu trainer.devices=2`).

The processes are Lightning's: its launcher starts them (it runs launch.py again with LOCAL_RANK
set), its process group joins them (NCCL on GPUs, gloo on the CPU) and its strategy collectives
(all_gather, reduce, broadcast, barrier) carry everything below. What is ours:

* `EditDDPStrategy`: Lightning's DDPStrategy without the DistributedDataParallel wrapper. DDP fixes
  its gradient buckets to the parameter shapes it first sees, and densification changes the
  number of Gaussians (`IndexSelectBackward0 returned an invalid gradient ... [9794, 0, 3] but
  expected ... [9765, 0, 3]`). The edit optimises manually, so it sums the gradients itself
  (`reduce_step`) after its backward passes.
* the split of a stage's views (`share`, `map_views`): each process runs its share (items rank,
  rank + world, ...) and the results are all_gathered in item order. A view's result depends on
  the view (its seed, its camera), never on the process that made it.
* the training step (`StepStats`, `reduce_step`): the gradients of the step's views summed over
  the processes and averaged, the densification statistics of the step summed (view-space
  gradient norms, counts) or maxed (screen radii), so that every process takes the same optimizer
  step, makes the same densify and prune decisions and holds the same Gaussians.
* work counters summed over the processes (`sum_increments`); rank 0's answer where every process
  computed the same thing (`from_rank_zero`), rank 0's RNG for densification's split samples
  (`agree_on_rng`), and a check that the processes still agree (`check_agree`).
* each process's GPU made current before its priors load (`use_process_gpu`);
* the trial directory handed down to the processes the launcher starts (`hand_down_trial`,
  `handed_down_trial`): launch.py runs again in each, and must use rank 0's trial, not make one.

With one process every helper returns at once and changes nothing: a single-process run is the
same, bit for bit, as before data parallelism existed.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import torch
from lightning.pytorch.strategies import DDPStrategy

from gs_regional.config import ConfigError

TRIAL_DIR_ENV = "GS_REGIONAL_TRIAL_DIR"  # rank 0's trial dir, for the processes Lightning launches
TIMESTAMP_ENV = "GS_REGIONAL_TRIAL_TIMESTAMP"  # and its timestamp (configs, log folders)


class EditDDPStrategy(DDPStrategy):
    """Lightning's DDP (launcher, process group, collectives, rank-zero checkpoints) with the
    LightningModule left unwrapped: the system reduces its own gradients (`reduce_step`), so the
    number of Gaussians may change between steps as long as every process changes it alike."""

    def configure_ddp(self) -> None:
        # No DistributedDataParallel: its reducer is built for the parameter shapes of step 0.
        pass


# ----------------------------------------------------------------------------- ranks
def _trainer(module: Any) -> Any:
    try:
        return module.trainer
    except RuntimeError:  # not attached (Lightning's `trainer` raises then)
        return None


def rank_and_world(module: Any) -> Tuple[int, int]:
    """(global rank, world size) of the run `module` is in; (0, 1) outside a trainer."""
    trainer = _trainer(module)
    if trainer is None:
        return 0, 1
    return int(trainer.global_rank), int(trainer.world_size)


def world_size(module: Any) -> int:
    return rank_and_world(module)[1]


def is_rank_zero(module: Any) -> bool:
    """Whether this process writes the run's outputs (the only one with one process)."""
    return rank_and_world(module)[0] == 0


def _strategy(module: Any) -> Any:
    return module.trainer.strategy


# ----------------------------------------------------------------------------- the split of views
def share(n: int, rank: int, world: int) -> List[int]:
    """The items of range(n) that process `rank` of `world` works on: rank, rank + world, ...
    (every process gets n // world or one more, near and far views alike)."""
    if world < 1 or not 0 <= rank < world:
        raise ValueError(f"share: rank {rank} of a world of {world} processes")
    return list(range(rank, n, world))


def gather_shares(module: Any, local: torch.Tensor, n: int) -> torch.Tensor:
    """(n, ...) the results of every process's `share` of range(n), in item order: `local` holds
    this process's (len(share), ...) results, all of one shape and dtype on every process."""
    rank, world = rank_and_world(module)
    rows = -(-n // world)
    if local.shape[0] != len(share(n, rank, world)):
        raise ValueError(f"gather_shares: {local.shape[0]} results for a share of {len(share(n, rank, world))} items")
    pad = local.new_zeros((rows - local.shape[0], *local.shape[1:]))
    padded = torch.cat([local, pad]) if pad.shape[0] else local
    gathered = _strategy(module).all_gather(padded.contiguous())  # (world, rows, ...)
    return torch.stack([gathered[i % world, i // world] for i in range(n)]) if n else local[:0]


def map_views(module: Any, n: int, fn: Callable[[List[int]], torch.Tensor], item_shape: Sequence[int],
              dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """`fn(items)` -> (len(items), *item_shape) for this process's share of range(n), gathered
    from every process in item order: (n, *item_shape). One process: `fn(list(range(n)))`.
    `fn` must give every item the result it would get alone (per-view seeds, no shared state)."""
    rank, world = rank_and_world(module)
    if world == 1:
        return fn(list(range(n)))
    mine = share(n, rank, world)
    if mine:
        local = fn(mine)
    else:
        local = torch.empty((0, *item_shape), dtype=dtype, device=module.device)
    return gather_shares(module, local.to(module.device), n)


def sum_increments(module: Any, before: Dict[str, int], after: Dict[str, int]) -> Dict[str, int]:
    """Counters after a stage whose work was shared out: `before` (the same on every process)
    plus every process's increment `after - before`. The keys of `after` must be the same on
    every process."""
    if world_size(module) == 1:
        return dict(after)
    keys = sorted(after)
    inc = torch.tensor([float(after[k] - before.get(k, 0)) for k in keys], dtype=torch.float64, device=module.device)
    _strategy(module).reduce(inc, reduce_op="sum")
    return {k: int(before.get(k, 0) + round(v)) for k, v in zip(keys, inc.tolist())}


def from_rank_zero(module: Any, value: Any) -> Any:
    """Rank 0's `value` on every process (a tensor comes back on this process's device): where
    every process computes the same decision, they take one answer (renders on a GPU add in an
    order that may differ between processes, and a threshold could tip differently)."""
    if world_size(module) == 1:
        return value
    if isinstance(value, torch.Tensor):
        device = value.device
        return _strategy(module).broadcast(value.detach().cpu(), src=0).to(device)
    return _strategy(module).broadcast(value, src=0)


def agree_on_rng(module: Any) -> None:
    """Every process takes rank 0's torch RNG state (the CPU's and the module's CUDA device's):
    draws from the global RNG (densification's split samples) are then the same on every process,
    and the same as one process would draw."""
    if world_size(module) == 1:
        return
    torch.set_rng_state(from_rank_zero(module, torch.get_rng_state()))
    device = torch.device(module.device)
    if device.type == "cuda":
        torch.cuda.set_rng_state(from_rank_zero(module, torch.cuda.get_rng_state(device)), device)


def check_agree(module: Any, what: str, values: Sequence[float]) -> None:
    """Raise if the processes hold different `values` (e.g. Gaussian counts) after `what`: they
    would go on with different parameter shapes and hang or fail in the next collective."""
    if world_size(module) == 1:
        return
    mine = torch.tensor([float(v) for v in values], dtype=torch.float64, device=module.device)
    every = _strategy(module).all_gather(mine)  # (world, k)
    if not bool((every == every[0]).all()):
        per_rank = "; ".join(f"rank {r}: {[round(v, 6) for v in row]}" for r, row in enumerate(every.tolist()))
        raise RuntimeError(
            f"data-parallel edit: the processes disagree after {what} ({per_rank}); every process must hold the "
            "same Gaussians. Run on one device, or with trainer.deterministic=true"
        )


# ----------------------------------------------------------------------------- the training step
class StepStats:
    """A step's densification statistics kept apart from the sums before it: the model's
    `grad_accum` and `grad_count` restart from zero for the step, and `finish` adds the step's
    increments of every process back onto the kept sums (and the screen radii's maximum over the
    processes). The same arithmetic with one process, so one process with k views per step and k
    processes with one each sum alike."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.accum, self.count = model.grad_accum, model.grad_count
        model.grad_accum = torch.zeros_like(self.accum)
        model.grad_count = torch.zeros_like(self.count)

    def finish(self, module: Any) -> None:
        m = self.model
        inc = torch.stack([m.grad_accum, m.grad_count.to(m.grad_accum.dtype)])
        if world_size(module) > 1:
            _strategy(module).reduce(inc, reduce_op="sum")
            radii = m.max_radii2d.clone()
            _strategy(module).reduce(radii, reduce_op="max")
            m.max_radii2d = radii
        m.grad_accum = self.accum + inc[0]
        m.grad_count = self.count + inc[1].to(self.count.dtype)


def reduce_step(module: Any, params: Sequence[torch.nn.Parameter], n_views: int, loss_sum: torch.Tensor,
                stats: Optional[StepStats] = None) -> torch.Tensor:
    """After this process's backward passes of a step over `n_views` views (its share of them):
    every parameter's gradient summed over the processes and divided by `n_views` (the gradient
    of the views' mean loss; a parameter no process has a gradient for keeps None), the step's
    densification statistics summed (`stats`). Returns the mean loss of the step's views."""
    world = world_size(module)
    if world > 1:
        strategy = _strategy(module)
        flags = torch.tensor([float(p.grad is not None) for p in params] + [float(loss_sum)], dtype=torch.float64,
                             device=module.device)
        strategy.reduce(flags, reduce_op="sum")
        for p, has in zip(params, flags[:-1].tolist()):
            if has == 0:
                continue
            if p.grad is None:
                p.grad = torch.zeros_like(p)
            if p.grad.numel():
                strategy.reduce(p.grad, reduce_op="sum")
        loss_sum = flags[-1]
    if stats is not None:
        stats.finish(module)
    if n_views > 1:
        for p in params:
            if p.grad is not None:
                p.grad.div_(n_views)
    return (loss_sum / n_views).float()


# ----------------------------------------------------------------------------- launch
def requested_processes(kw: Dict[str, Any]) -> int:
    """The processes a Trainer with arguments `kw` would run (devices x num_nodes), read with
    Lightning's own device parsing; a GPU list that this machine does not have is a ConfigError."""
    accelerator = str(kw.get("accelerator") or "auto").lower()
    devices = kw.get("devices", "auto")
    nodes = int(kw.get("num_nodes", 1) or 1)
    if accelerator == "auto":
        accelerator = "cuda" if torch.cuda.is_available() else "cpu"
    if devices in (None, "auto"):  # Lightning's default: one CPU process, or every GPU
        devices = max(torch.cuda.device_count(), 1) if accelerator in ("gpu", "cuda") else 1
    if accelerator == "cpu":
        from lightning.pytorch.accelerators import CPUAccelerator

        try:
            return int(CPUAccelerator.parse_devices(devices)) * nodes
        except Exception as e:  # noqa: BLE001 - Lightning's MisconfigurationException, TypeError
            raise ConfigError(f"trainer.devices={devices!r}: {e}") from None
    if accelerator in ("gpu", "cuda"):
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        from lightning.pytorch.accelerators import CUDAAccelerator

        try:
            ids = CUDAAccelerator.parse_devices(devices)
        except Exception as e:  # noqa: BLE001 - Lightning says which GPUs it could not find
            reason = " ".join(str(e).split())
            raise ConfigError(f"trainer.devices={devices!r} (--gpu): this machine has {available} CUDA GPU(s): "
                              f"{reason}") from None
        return max(len(ids or []), 1) * nodes
    return nodes  # other accelerators: left to Lightning, one process per node


def check_gpu_list(gpu_ids: Sequence[int], cuda_available: bool, device_count: int) -> None:
    """`--gpu 0,1`: every index must be a GPU of this machine (one index on a machine without
    CUDA falls back to the CPU with a warning; a list does not)."""
    if len(gpu_ids) > 1 and not cuda_available:
        raise ConfigError(
            f"--gpu {','.join(map(str, gpu_ids))} asks for {len(gpu_ids)} GPUs but CUDA is not available on this "
            f"machine; to share an edit over {len(gpu_ids)} processes on the CPU give "
            f"trainer.accelerator=cpu trainer.devices={len(gpu_ids)}"
        )
    missing = [i for i in gpu_ids if cuda_available and i >= device_count]
    if missing:
        raise ConfigError(
            f"--gpu {','.join(map(str, gpu_ids))}: this machine has {device_count} CUDA GPU(s) "
            f"(indices 0..{device_count - 1}); there is no GPU {', '.join(map(str, missing))}"
        )


def use_process_gpu(trainer_cfg: Dict[str, Any], gpu: Optional[str]) -> None:
    """Before the system and its priors are built, make this process's GPU the current CUDA
    device: priors on device "auto" (or "cuda") then load onto the GPU that Lightning gives this
    process (entry LOCAL_RANK of the device list; rank 0 takes the first), not all onto GPU 0.
    `trainer_cfg` is the `trainer:` section, `gpu` launch.py's --gpu. Nothing on the CPU, and
    nothing for settings that trainer_kwargs will refuse."""
    if not torch.cuda.is_available():
        return
    kw = dict(trainer_cfg)
    try:
        if "accelerator" not in kw:  # as trainer_kwargs: --gpu picks the GPUs, else the CPU
            if gpu is None:
                return
            kw["accelerator"] = "gpu"
            kw.setdefault("devices", [int(g) for g in str(gpu).split(",") if g.strip()])
        if str(kw["accelerator"]).lower() not in ("gpu", "cuda", "auto"):
            return
        from lightning.pytorch.accelerators import CUDAAccelerator

        devices = kw.get("devices", 1)
        ids = CUDAAccelerator.parse_devices(-1 if devices in (None, "auto") else devices) or []
    except Exception:  # noqa: BLE001 - trainer_kwargs and Lightning say what is wrong
        return
    local = int(os.environ.get("LOCAL_RANK", "0") or 0)
    if local < len(ids):
        torch.cuda.set_device(ids[local])


def handed_down_trial() -> Optional[Tuple[Path, str]]:
    """(trial dir, timestamp) in a process that Lightning's launcher started for rank 0's run
    (LOCAL_RANK > 0 and the trial handed down); None in rank 0 and in a single-process run."""
    trial = os.environ.get(TRIAL_DIR_ENV)
    if not trial or int(os.environ.get("LOCAL_RANK", "0") or 0) == 0:
        return None
    return Path(trial), os.environ.get(TIMESTAMP_ENV, "")


@contextlib.contextmanager
def hand_down_trial(trial: Path, timestamp: str) -> Iterator[None]:
    """While rank 0's `trainer.fit` runs: the environment the launcher copies into the processes
    it starts names rank 0's trial dir and timestamp (restored afterwards)."""
    old = {k: os.environ.get(k) for k in (TRIAL_DIR_ENV, TIMESTAMP_ENV)}
    os.environ[TRIAL_DIR_ENV] = str(trial)
    os.environ[TIMESTAMP_ENV] = timestamp or ""
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
