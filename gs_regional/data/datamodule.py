"""`scene-datamodule`: cameras (and photos, when present) of a real scene folder."""
from __future__ import annotations

import os
import random
from dataclasses import dataclass
from typing import Iterator, Optional

import lightning as L
from torch.utils.data import DataLoader, Dataset, IterableDataset

from gs_regional.config import ConfigError
from gs_regional.data.scene import SceneData, split_every
from gs_regional.registry import register


class EndlessIndices(IterableDataset):
    """Training steps are driven by the system; the loader only ticks with a seeded view index."""

    def __init__(self, indices, seed: int = 0) -> None:
        self.indices = list(indices)
        self.seed = seed

    def __iter__(self) -> Iterator[dict]:
        rng = random.Random(self.seed)
        while True:
            order = list(self.indices)
            rng.shuffle(order)
            for i in order:
                yield {"index": i}


class FixedIndices(Dataset):
    def __init__(self, indices) -> None:
        self.indices = list(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, k: int) -> dict:
        return {"index": self.indices[k]}


class SceneDataModuleBase(L.LightningDataModule):
    """Shared loaders; subclasses build `self.scene` (a SceneData, with its optional
    `ground_truth` when they know the scene's edit) in `setup()`."""

    scene: Optional[SceneData] = None

    def train_dataloader(self) -> DataLoader:
        return DataLoader(EndlessIndices(self.scene.train_indices or self.scene.test_indices), batch_size=None)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(FixedIndices(self.scene.test_indices or self.scene.train_indices[:1]), batch_size=None)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(FixedIndices(self.scene.test_indices or self.scene.train_indices), batch_size=None)

    def predict_dataloader(self) -> DataLoader:
        return self.test_dataloader()


@register("scene-datamodule")
class SceneDataModule(SceneDataModuleBase):
    @dataclass
    class Config:
        source: str = ""  # scene folder or camera file (COLMAP sparse/0, transforms.json, cameras.json)
        downscale: float = 1.0  # 4 = images and intrinsics 4x smaller
        test_every: int = 8  # every n-th camera is held out for evaluation (0: none)
        load_images: bool = True  # photos are needed to fit a scene, not to edit one
        max_cameras: int = 0  # 0 = all; else an evenly spread subset (for quick runs)

    def __init__(self, cfg=None) -> None:
        super().__init__()
        from gs_regional.config import parse_structured

        self.cfg = parse_structured(self.Config, cfg, where="data")
        if not self.cfg.source:
            raise ConfigError("data.source is not set: give a scene folder or camera file (data.source=path/to/scene)")
        if not os.path.exists(self.cfg.source):
            raise ConfigError(f"data.source does not exist: {self.cfg.source}")
        if self.cfg.downscale <= 0:
            raise ConfigError(f"data.downscale must be > 0, got {self.cfg.downscale}")

    def setup(self, stage: Optional[str] = None) -> None:
        if self.scene is not None:
            return
        from gs_regional.data.images import load_image
        from gs_regional.data.loaders import load_cameras
        from gs_regional.data.points import load_points

        cameras = load_cameras(self.cfg.source)
        if self.cfg.max_cameras and len(cameras) > self.cfg.max_cameras:
            step = len(cameras) / self.cfg.max_cameras
            cameras = [cameras[int(i * step)] for i in range(self.cfg.max_cameras)]
        if self.cfg.downscale != 1.0:
            cameras = [c.scaled(1.0 / self.cfg.downscale) for c in cameras]
        images = None
        if self.cfg.load_images and all(c.image_path for c in cameras):
            images = [load_image(c) for c in cameras]
        train, test = split_every(len(cameras), self.cfg.test_every)
        folder = self.cfg.source if os.path.isdir(self.cfg.source) else os.path.dirname(self.cfg.source)
        self.scene = SceneData(
            cameras=cameras,
            images=images,
            train_indices=train,
            test_indices=test,
            points=load_points(folder),
            source=self.cfg.source,
        )
