"""Base classes: every component has a nested `Config` dataclass parsed strictly."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch.nn as nn

from gs_regional.config import parse_structured


class Configurable:
    @dataclass
    class Config:
        pass

    cfg: Any

    def __init__(self, cfg: Any = None, where: str = "") -> None:
        self.cfg = parse_structured(self.Config, cfg, where=where, label=type(self).__name__)


class BaseModule(nn.Module):
    """An nn.Module component with a typed config."""

    @dataclass
    class Config:
        pass

    cfg: Any

    def __init__(self, cfg: Any = None, where: str = "") -> None:
        super().__init__()
        self.cfg = parse_structured(self.Config, cfg, where=where, label=type(self).__name__)


def component_name(obj: Any) -> str:
    """The name a component is registered under (its class name when it is not registered), for
    error messages."""
    return type(obj).__dict__.get("registered_name", type(obj).__name__)
