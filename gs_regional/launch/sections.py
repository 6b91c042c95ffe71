"""The Config dataclass of a registered type, for the section beside a `*_type` key: a type
switched on the command line drops the keys of the YAML's old type, and every such section is
checked before anything is built (gs_regional.config.load_config does both)."""
from __future__ import annotations

from dataclasses import is_dataclass
from typing import List, Optional

from gs_regional.registry import RegistryError, find

# The registry kind of each `*_type` key of the built-in configs (the last part of the key).
TYPE_KINDS = {
    "data_type": "data", "system_type": "systems", "geometry_type": "geometry",
    "renderer_type": "renderers", "guidance_type": "guidance", "depth_type": "depth",
}


def _config(cls: type) -> Optional[type]:
    config = getattr(cls, "Config", None)
    return config if config is not None and is_dataclass(config) else None


def section_configs(type_key: str, name: str) -> Optional[List[type]]:
    """The Config dataclasses that type `name` of `type_key` (e.g. "system.guidance_type") reads
    its section with: one, or both candidates of `renderer_type: auto` (an option of either is
    accepted, select.py). None when that cannot be told: a class without a `Config` dataclass, or
    a plugin's own `*_type` key whose value is not a registered name."""
    kind = TYPE_KINDS.get(type_key.rsplit(".", 1)[-1])
    if kind == "renderers":
        from gs_regional.renderers.select import AUTO, AUTO_CANDIDATES

        if name == AUTO:
            configs = [_config(find(c, kind=kind, key=type_key)) for c in AUTO_CANDIDATES]
            return None if any(c is None for c in configs) else configs
    if kind is None:
        try:
            cls = find(name)
        except RegistryError:
            return None
    else:
        cls = find(name, kind=kind, key=type_key)  # an unknown name fails now, as it would later
    config = _config(cls)
    return None if config is None else [config]
