"""Typed, strictly parsed configuration (OmegaConf structured configs) and scheduled scalars."""
from __future__ import annotations

import os
from dataclasses import dataclass, field, is_dataclass
from typing import Any, List, Optional, Sequence, Type, TypeVar, Union

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration problem; the message names the file or key at fault."""


def parse_structured(cfg_cls: Type[T], cfg: Any = None, where: str = "") -> T:
    """Merge a plain/OmegaConf mapping into the dataclass `cfg_cls`, rejecting unknown keys.

    `where` names the YAML section (e.g. "system.geometry") so errors point at the full key.
    """
    assert is_dataclass(cfg_cls), cfg_cls
    if isinstance(cfg, cfg_cls):
        return cfg
    base = OmegaConf.structured(cfg_cls)
    if cfg is None:
        cfg = {}
    if is_dataclass(cfg):
        cfg = OmegaConf.structured(cfg)
    try:
        merged = OmegaConf.merge(base, cfg)
    except ConfigKeyError as e:
        key = f"{where}.{e.key}" if where else str(e.key)
        allowed = ", ".join(sorted(base.keys()))
        raise ConfigError(
            f"unknown config key '{key}' for {cfg_cls.__qualname__}; allowed keys: {allowed}"
        ) from None
    except ValidationError as e:
        key = f"{where}.{e.full_key}" if where else str(e.full_key)
        raise ConfigError(f"bad value for config key '{key}': {e.msg}") from None
    except OmegaConfBaseException as e:
        raise ConfigError(f"config error in '{where or cfg_cls.__qualname__}': {e}") from None
    # Turn into a real dataclass instance; nested untyped dicts stay DictConfigs.
    return OmegaConf.to_object(merged)


def to_container(cfg: Any) -> Any:
    if isinstance(cfg, DictConfig) or OmegaConf.is_config(cfg):
        return OmegaConf.to_container(cfg, resolve=True)
    if is_dataclass(cfg):
        return OmegaConf.to_container(OmegaConf.structured(cfg), resolve=True)
    return cfg


def scheduled(value: Union[float, int, Sequence], step: int) -> float:
    """A scalar that may change with the step (threestudio's ``C``).

    * a number is constant;
    * ``[start_step, start_value, end_value, end_step]`` ramps linearly and holds at both ends;
    * ``[[step0, v0], [step1, v1], ...]`` is piecewise constant: the value of the last step <= step.
    """
    if isinstance(value, (int, float)):
        return float(value)
    value = list(value)
    if value and isinstance(value[0], (list, tuple)) or (value and OmegaConf.is_list(value[0])):
        current = float(value[0][1])
        for s, v in value:
            if step >= s:
                current = float(v)
        return current
    if len(value) != 4:
        raise ConfigError(
            f"a scheduled value must be a number, [start_step, start_value, end_value, end_step] "
            f"or [[step, value], ...]; got {value}"
        )
    s0, v0, v1, s1 = value
    if step <= s0:
        return float(v0)
    if step >= s1:
        return float(v1)
    t = (step - s0) / max(s1 - s0, 1)
    return float(v0 + (v1 - v0) * t)


@dataclass
class ExperimentConfig:
    """Top level of every YAML file in configs/."""

    name: str = "default"
    tag: str = ""
    description: str = ""
    seed: int = 0
    exp_root_dir: str = "outputs"
    use_timestamp: bool = True
    timestamp: str = ""  # filled at launch
    trial_dir: str = ""  # filled at launch: <exp_root_dir>/<name>/<tag>@<timestamp>
    resume: Optional[str] = None
    data_type: str = "scene-datamodule"
    data: dict = field(default_factory=dict)
    system_type: str = ""
    system: dict = field(default_factory=dict)
    trainer: dict = field(default_factory=dict)
    checkpoint: dict = field(default_factory=dict)


def load_config(path: str, overrides: Optional[List[str]] = None) -> DictConfig:
    """Read a YAML config and apply `key=value` overrides (OmegaConf dotlist)."""
    if not os.path.isfile(path):
        raise ConfigError(f"config file not found: {path}")
    try:
        yaml_cfg = OmegaConf.load(path)
    except Exception as e:  # yaml errors carry the line number
        raise ConfigError(f"cannot parse config file {path}: {e}") from None
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
    try:
        cli = OmegaConf.from_dotlist(list(overrides or []))
    except Exception as e:
        raise ConfigError(f"bad command-line override: {e}") from None
    merged = OmegaConf.merge(yaml_cfg, cli)
    # Validate the top level now; component sections are validated by their components.
    parse_structured(ExperimentConfig, merged, where="")
    return merged
