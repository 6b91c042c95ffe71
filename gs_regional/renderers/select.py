"""Choosing the renderer of a system: a registered name, or `auto`.

`renderer_type: auto` is gsplat's CUDA kernels where they can run (the module is placed on a CUDA
device and gsplat imports), the pure-PyTorch `torch-rasterizer` otherwise; the choice is logged.
It is made for the device the trainer places the module on (known in `setup()`), not for whether
the machine has a GPU: a run on the CPU of a GPU machine (launch.py without --gpu) must not pick
kernels that reject CPU tensors.

Renderer options shared by both (Renderer.Config: background, tile size, planes, eps2d) apply to
whichever is chosen. With `auto`, an option that only the other candidate has (e.g. the torch
rasterizer's `strip_width`) is left out, and the log line says so; a key no candidate knows is an
error as for any renderer.
"""
from __future__ import annotations

import logging
from dataclasses import fields
from typing import Any, Dict, Tuple

import torch

from gs_regional.config import parse_structured, to_container
from gs_regional.registry import find
from gs_regional.renderers import gsplat_rasterizer
from gs_regional.renderers.base import Renderer

log = logging.getLogger(__name__)

AUTO = "auto"
AUTO_CANDIDATES = ("gsplat-rasterizer", "torch-rasterizer")


def resolve_renderer_type(name: str, device: torch.device) -> Tuple[str, str]:
    """(registered renderer name, why) for `name` on `device`; `auto` decides as the module says."""
    if name != AUTO:
        return name, "as configured"
    device = torch.device(device)
    if device.type != "cuda":
        return "torch-rasterizer", f"the module runs on {device}"
    if gsplat_rasterizer._gsplat is None:
        err = gsplat_rasterizer._GSPLAT_IMPORT_ERROR
        return "torch-rasterizer", f"gsplat does not import ({type(err).__name__}: {err})"
    return "gsplat-rasterizer", f"the module runs on {device} and gsplat imports"


def _option_names(name: str) -> set:
    return {f.name for f in fields(find(name, kind="renderers").Config)}


def renderer_options(name: str, options: Any, chosen: str) -> Tuple[Dict[str, Any], list]:
    """The `options` (system.renderer) that renderer `chosen` takes, and the keys left out: with
    `auto` those only another candidate knows; otherwise nothing is left out."""
    options = dict(to_container(options) or {})
    if name != AUTO:
        return options, []
    known = _option_names(chosen)
    others = set().union(*(_option_names(c) for c in AUTO_CANDIDATES if c != chosen))
    dropped = sorted(k for k in options if k not in known and k in others)
    return {k: v for k, v in options.items() if k not in dropped}, dropped


def check_renderer_config(name: str, options: Any, where: str = "system.renderer") -> None:
    """Fail at start-up on an unknown renderer name or option, before anything is built: with
    `auto`, every option must belong to one of the candidates."""
    candidates = AUTO_CANDIDATES if name == AUTO else (name,)
    for chosen in candidates:
        kept, _ = renderer_options(name, options, chosen)
        parse_structured(find(chosen, kind="renderers", key=f"{where}_type").Config, kept, where=where)


def make_renderer(name: str, options: Any, device: torch.device, where: str = "system.renderer") -> Renderer:
    """Build renderer `name` (or the one `auto` picks for `device`) with its `options`."""
    chosen, why = resolve_renderer_type(name, device)
    kept, dropped = renderer_options(name, options, chosen)
    if name == AUTO:
        unused = f"; options only the other renderer takes are not used: {', '.join(dropped)}" if dropped else ""
        log.info("renderer_type auto: %s (%s)%s", chosen, why, unused)
    return find(chosen, kind="renderers")(kept, where=where)
