"""State declared once: a dataclass whose fields are saved in checkpoints, loaded and moved to the
module's device generically (tensors, and lists and dicts of them, go to the CPU in a checkpoint)."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Dict, List, Optional

import torch


def _map(value: Any, fn) -> Any:
    if isinstance(value, torch.Tensor):
        return fn(value)
    if isinstance(value, list):
        return [_map(v, fn) for v in value]
    if isinstance(value, dict):
        return {k: _map(v, fn) for k, v in value.items()}
    return value


class Saved:
    """Mixin of a state dataclass. A field's metadata may say `saved=False` (never in checkpoints)
    or `saved_in_phase="..."` (saved only while the state's `phase` is that; None otherwise)."""

    def state_dict(self) -> Dict[str, Any]:
        out = {}
        for f in fields(self):
            if not f.metadata.get("saved", True):
                continue
            phase = f.metadata.get("saved_in_phase")
            value = getattr(self, f.name) if phase is None or getattr(self, "phase", None) == phase else None
            out[f.name] = _map(value, lambda t: t.cpu())
        return out

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        for f in fields(self):
            if f.name in state and f.metadata.get("saved", True):
                setattr(self, f.name, state[f.name])

    def to(self, device) -> "Saved":
        for f in fields(self):
            setattr(self, f.name, _map(getattr(self, f.name), lambda t: t.to(device)))
        return self


@dataclass
class EditState(Saved):
    """What a regional edit knows between its stages (all of it goes into checkpoints)."""

    phase: str = "localize"  # localize -> initialize -> refine -> done
    localize_views: List[int] = field(default_factory=list)
    localize_metrics: Dict[str, Any] = field(default_factory=dict)
    source_selection: Optional[torch.Tensor] = None  # (n_source,) bool, set by localization
    # The 2D masks choose the first view: needed by a resume between localize and initialize.
    masks2d: Optional[torch.Tensor] = field(default=None, metadata={"saved_in_phase": "initialize"})
    localized_masks: Dict[int, torch.Tensor] = field(default_factory=dict, metadata={"saved": False})  # view -> (H, W) bool
    v_first: Optional[int] = None
    first_edit: Optional[torch.Tensor] = None  # the first view's full edit
    init_report: Optional[Dict[str, Any]] = None
    refine_start_count: int = 0
    edited_views: List[int] = field(default_factory=list)
    cycle_views: List[int] = field(default_factory=list)
    cycle_targets: Optional[torch.Tensor] = None  # (k, H, W, 3) edited views of a cycle
    cycle_weights: Optional[torch.Tensor] = None  # (k, H, W) how much each target pixel counts in training (None: alike)
    targets_cycle: int = -1
