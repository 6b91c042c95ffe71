"""Typed, strictly parsed configuration (OmegaConf structured configs) and scheduled scalars."""
from __future__ import annotations

import difflib
import numbers
import os
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, List, Optional, Sequence, Type, TypeVar, Union

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration problem; the message names the file or key at fault."""


def _full_key(where: str, e: OmegaConfBaseException) -> str:
    key = getattr(e, "full_key", None) or getattr(e, "key", None)
    key = "" if key is None else str(key)
    return ".".join(k for k in (where, key) if k)


def _first_line(e: OmegaConfBaseException) -> str:
    """OmegaConf messages append 'full_key: ... object_type=...' lines; keep the sentence."""
    msg = getattr(e, "msg", None) or str(e)
    return str(msg).strip().splitlines()[0] if str(msg).strip() else type(e).__name__


def parse_structured(cfg_cls: Type[T], cfg: Any = None, where: str = "") -> T:
    """Merge a plain/OmegaConf mapping into the dataclass `cfg_cls`, rejecting unknown keys.

    A dataclass may name keys that moved elsewhere in a class attribute `MOVED_KEYS`
    ({old key: new full key}); using one fails with the new name.

    `where` names the YAML section (e.g. "system") so errors point at the full key
    (e.g. 'system.geometry.plyy', also inside nested dataclasses).
    """
    assert is_dataclass(cfg_cls), cfg_cls
    if isinstance(cfg, cfg_cls):
        return cfg
    base = OmegaConf.structured(cfg_cls)
    if cfg is None:
        cfg = {}
    if is_dataclass(cfg):
        cfg = OmegaConf.structured(cfg)
    if not isinstance(cfg, (dict, DictConfig)):
        raise ConfigError(
            f"config section '{where or cfg_cls.__qualname__}' must be a mapping of keys to values, "
            f"got {type(cfg).__name__}: {cfg!r}"
        )
    try:
        merged = OmegaConf.merge(base, cfg)
        # Turn into a real dataclass instance (this also resolves ${...} interpolations);
        # nested untyped dicts stay DictConfigs.
        return OmegaConf.to_object(merged)
    except ConfigKeyError as e:
        key = _full_key(where, e)
        owner = getattr(e, "object_type", None)
        owner = owner if owner is not None and is_dataclass(owner) else cfg_cls
        moved = getattr(owner, "MOVED_KEYS", {}).get(str(e.key))
        if moved:
            raise ConfigError(f"config key '{key}' has moved: use '{moved}'") from None
        allowed = sorted(f.name for f in fields(owner))
        close = difflib.get_close_matches(str(e.key), allowed, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ConfigError(
            f"unknown config key '{key}'{hint} for {owner.__qualname__}; allowed keys: {', '.join(allowed)}"
        ) from None
    except ValidationError as e:
        key = _full_key(where, e)
        if key and key != where:
            raise ConfigError(f"bad value for config key '{key}': {_first_line(e)}") from None
        raise ConfigError(f"bad value in config section '{where or cfg_cls.__qualname__}': {_first_line(e)}") from None
    except OmegaConfBaseException as e:
        key = _full_key(where, e) or cfg_cls.__qualname__
        raise ConfigError(f"config error at '{key}': {_first_line(e)}") from None


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
    if isinstance(value, numbers.Real):  # also numpy scalars and bools
        return float(value)
    if isinstance(value, str) or not hasattr(value, "__iter__"):
        raise ConfigError(f"a scheduled value must be a number or a list, got {value!r}")
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
    """Read a YAML config, apply `key=value` overrides (OmegaConf dotlist) and return it merged
    onto the `ExperimentConfig` defaults with every `${...}` interpolation resolved.

    The top level is validated here; component sections are validated by their components.
    """
    if not os.path.isfile(path):
        raise ConfigError(f"config file not found: {path}")
    try:
        yaml_cfg = OmegaConf.load(path)
    except Exception as e:  # yaml errors carry the line number
        raise ConfigError(f"cannot parse config file {path}: {e}") from None
    if not isinstance(yaml_cfg, DictConfig):
        raise ConfigError(f"config file {path} must hold a mapping of keys to values at the top level")
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
    try:
        cli = OmegaConf.from_dotlist(list(overrides or []))
        merged = OmegaConf.merge(yaml_cfg, cli)
    except Exception as e:
        raise ConfigError(f"bad command-line override: {str(e).splitlines()[0]}") from None
    try:
        parse_structured(ExperimentConfig, merged, where="")
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    cfg = OmegaConf.merge(OmegaConf.structured(ExperimentConfig), merged)
    try:
        OmegaConf.resolve(cfg)  # so that sections handed to components stand alone
    except OmegaConfBaseException as e:
        raise ConfigError(f"{path}: config error at '{_full_key('', e)}': {_first_line(e)}") from None
    return cfg
