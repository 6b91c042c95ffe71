"""`in2n`: the whole-scene baseline (Instruct-NeRF2NeRF / Instruct-GS2GS iterative dataset update).

No localization and no initialization: every `edit_every` steps one training view is re-edited
from the current render at a random start timestep in [t_min, t_max]·T, conditioned on the
original view, and every Gaussian is finetuned on the (partly edited) dataset.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from gs_regional.config import ConfigError
from gs_regional.registry import register
from gs_regional.systems.edit_base import EditSystemBase


@register("in2n")
class In2N(EditSystemBase):
    @dataclass
    class Config(EditSystemBase.Config):
        max_steps: int = 1500
        edit_every: int = 10
        t_min: float = 0.70
        t_max: float = 0.98
        num_train_timesteps: int = 1000

    def __init__(self, cfg=None, resumed: bool = False) -> None:
        super().__init__(cfg, resumed=resumed)
        self.configure()
        if not 0 < self.cfg.t_min <= self.cfg.t_max <= 1:
            raise ConfigError(f"system.t_min/t_max must satisfy 0 < t_min <= t_max <= 1, got {self.cfg.t_min}, {self.cfg.t_max}")
        self.dataset: torch.Tensor | None = None  # (V, H, W, 3) current targets of the train views
        self.edits_done = 0

    @property
    def total_steps(self) -> int:
        return self.cfg.max_steps

    def training_step(self, batch, batch_idx):
        cfg, scene = self.cfg, self.scene
        if self.dataset is None:
            self.dataset = torch.stack([self.source_renders[i] for i in scene.train_indices])
        step = self.global_step
        gen = torch.Generator().manual_seed(cfg.seed * 104729 + step)
        if step % cfg.edit_every == 0:
            self.set_stage("edit dataset")
            t0 = time.perf_counter()
            k = int(torch.randint(len(scene.train_indices), (1,), generator=gen))
            j = scene.train_indices[k]
            u = float(torch.rand((), generator=gen))
            t = int((cfg.t_min + (cfg.t_max - cfg.t_min) * u) * cfg.num_train_timesteps)
            with torch.no_grad():
                current = self.as_image(self.render_view(j)["rgb"], "the current renders")
                edited = self.guidance.edit(
                    current[None], self.source_renders[j][None], cfg.prompt, t_start=t, seed=cfg.seed + step, cameras=[scene.cameras[j]]
                )[0]
            self.dataset[k] = edited.to(self.dataset.device)
            self.edits_done += 1
            self.add_time("edit", time.perf_counter() - t0)
        self.set_stage("finetune")
        t0 = time.perf_counter()
        k = int(torch.randint(len(scene.train_indices), (1,), generator=gen))
        self.optimize_on(scene.train_indices[k], self.dataset[k])
        self.add_time("train", time.perf_counter() - t0)
        return None

    def on_train_end(self) -> None:
        self.counts["dataset_edits"] = self.edits_done
        self.write_outputs()

    def on_train_start(self) -> None:
        if self.dataset is not None:
            self.dataset = self.dataset.to(self.device)

    def extra_state(self) -> dict:
        dataset = None if self.dataset is None else self.dataset.cpu()
        return {**super().extra_state(), "dataset": dataset, "edits_done": self.edits_done}

    def load_extra_state(self, state: dict) -> None:
        super().load_extra_state(state)
        self.dataset = state.get("dataset")
        self.edits_done = state.get("edits_done", 0)
