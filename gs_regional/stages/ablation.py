"""`system.ablation`: the method's parts switched off one at a time, for measuring what each is
worth (gs_regional/bench/sweeps.py ABLATIONS, docs/method.md "Ablations"). No edit a user wants
needs them: every default is the method."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from gs_regional.config import need


@dataclass
class AblationConfig:
    localize: bool = True  # false selects every Gaussian (no localization)
    initialize: bool = True  # false adds no Gaussians from depth (refinement densifies instead)
    # For scenes with a known edit: the true region is the selection (localization still runs), to
    # measure what the rest of the method loses to localization.
    localize_with_truth: bool = False
    plain_vote: bool = False  # the paper's lift: no view re-weighting, no neighbour pooling, no evidence prior
    constant_t: Optional[int] = None  # one start timestep for every cycle instead of the schedules
    optimize_all: bool = False  # gradients reach every Gaussian (the paper's setting)
    composite: bool = True  # false trains on the whole edited views, the editor's changes outside the region too

    def check(self, where: str = "system.ablation", num_train_timesteps: int = 1000) -> None:
        if self.constant_t is not None:
            need(0 <= self.constant_t < num_train_timesteps, f"{where}.constant_t",
                 f"a timestep in [0, {num_train_timesteps - 1}]", self.constant_t)
