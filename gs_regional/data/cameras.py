"""The one camera type used everywhere (OpenCV convention: x right, y down, z forward)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional, Tuple

import numpy as np
import torch


@dataclass
class Camera:
    world_to_camera: torch.Tensor  # (4, 4) float32, OpenCV convention
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    image_name: str = ""
    image_path: Optional[str] = None  # where the photo is, if the scene has one
    # Lens distortion (k1, k2, p1, p2) of the *photo*; renders are always undistorted pinhole.
    distortion: Optional[Tuple[float, float, float, float]] = None

    def __post_init__(self) -> None:
        w2c = self.world_to_camera
        # A tensor keeps its device (np.asarray would fail on a CUDA one); anything else is read as an array.
        w2c = w2c.float() if isinstance(w2c, torch.Tensor) else torch.as_tensor(np.asarray(w2c), dtype=torch.float32)
        if w2c.shape != (4, 4):
            raise ValueError(f"camera '{self.image_name}': world_to_camera must be 4x4, got {tuple(w2c.shape)}")
        self.world_to_camera = w2c
        self.width, self.height = int(self.width), int(self.height)
        self.fx, self.fy, self.cx, self.cy = float(self.fx), float(self.fy), float(self.cx), float(self.cy)

    @property
    def K(self) -> torch.Tensor:
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float32
        )

    @property
    def camera_to_world(self) -> torch.Tensor:
        return torch.linalg.inv(self.world_to_camera.double()).float()

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, (3,)."""
        R = self.world_to_camera[:3, :3].double()
        t = self.world_to_camera[:3, 3].double()
        return (-R.T @ t).float()

    def project(self, points: torch.Tensor, near: float = 1e-3) -> tuple:
        """Image coordinates (u, v) in pixels and camera-space depth z, each (N,), of world points
        (N, 3) (points behind `near` are projected as if at `near`)."""
        w2c = self.world_to_camera.to(points.device, points.dtype)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = p[:, 2]
        return self.fx * p[:, 0] / z.clamp_min(near) + self.cx, self.fy * p[:, 1] / z.clamp_min(near) + self.cy, z

    def pixels(self, points: torch.Tensor, near: float = 1e-3) -> tuple:
        """(row, col, z, inside), each (N,), of world points (N, 3): the pixel each falls on (clamped
        into the image), its camera-space depth, and whether it lies in front of the camera and
        inside the image."""
        u, v, z = self.project(points, near)
        inside = (z > near) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return v.long().clamp(0, self.height - 1), u.long().clamp(0, self.width - 1), z, inside

    def in_view(self, points: torch.Tensor, near: float = 1e-3) -> torch.Tensor:
        """(N,) bool: which world points (N, 3) lie in front of the camera and inside its image."""
        return self.pixels(points, near)[3]

    def scaled(self, factor: float) -> "Camera":
        """The same camera with the image resized by `factor` (0.25 = 4x smaller)."""
        w = max(1, int(round(self.width * factor)))
        h = max(1, int(round(self.height * factor)))
        sx, sy = w / self.width, h / self.height
        return replace(
            self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h
        )

    def to(self, device) -> "Camera":
        return replace(self, world_to_camera=self.world_to_camera.to(device))

    @property
    def device(self) -> torch.device:
        return self.world_to_camera.device
