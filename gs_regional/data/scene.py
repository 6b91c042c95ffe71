"""What a datamodule hands to a system: the cameras, the photos (if any) and optional extras."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional, Sequence

import torch

from gs_regional.data.cameras import Camera


@dataclass
class SceneData:
    cameras: List[Camera]  # all cameras, at the working resolution
    images: Optional[Sequence[torch.Tensor]] = None  # (H, W, 3) in [0, 1] per camera, or None
    train_indices: List[int] = field(default_factory=list)
    test_indices: List[int] = field(default_factory=list)
    # SfM points for scenes without a trained splat: (xyz (N,3), rgb (N,3)) or None
    points: Optional[tuple] = None
    # The known edit of this scene, if any data module knows one (the synthetic scene does): a
    # gs_regional.sim.truth.GroundTruth (data/ sits below the simulators and never imports them).
    ground_truth: Optional[Any] = None
    source: str = ""  # where it came from, for messages

    def __post_init__(self) -> None:
        if not self.cameras:
            raise ValueError(f"scene '{self.source}' has no cameras")
        if not self.train_indices and not self.test_indices:
            self.train_indices = list(range(len(self.cameras)))

    @property
    def camera_centers(self) -> torch.Tensor:
        return torch.stack([c.center for c in self.cameras])

    @property
    def extent(self) -> float:
        """Radius of the camera rig around its centroid (the 3DGS 'scene extent')."""
        centers = self.camera_centers
        return float((centers - centers.mean(0)).norm(dim=-1).max() * 1.1)


def split_every(n: int, every: int) -> tuple:
    """Train/test split holding out every `every`-th camera (0 disables the hold-out)."""
    if every <= 0:
        return list(range(n)), []
    test = list(range(0, n, every))
    train = [i for i in range(n) if i % every != 0]
    return train, test
