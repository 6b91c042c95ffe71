"""Typed, strictly parsed configuration (OmegaConf structured configs) and scheduled scalars.

Command-line overrides (`key=value`) merge into the YAML, with two exceptions that make a section
replaceable from the command line:

* `section=null` clears a section of the YAML: the component's defaults apply, and keys given
  after it on the command line are kept (`system.guidance=null system.guidance.strength=0.5`);
* changing a `*_type` key (`system.guidance_type=grayscale-editor`) drops the keys of the YAML's
  section beside it that the new type does not take, with one log line naming them; keys given on
  the command line stay and are checked against the new type like any other.
"""
from __future__ import annotations

import difflib
import logging
import numbers
import os
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any, Callable, Collection, Dict, List, Optional, Sequence, Tuple, Type, TypeVar, Union

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException, ValidationError

T = TypeVar("T")
log = logging.getLogger(__name__)

TYPE_SUFFIX = "_type"  # `<section>_type` names the registered class that reads `<section>`


class ConfigError(ValueError):
    """A configuration problem; the message names the file or key at fault."""


def need(ok: bool, key: str, allowed: str, value: Any) -> None:
    """A component's range check at build time: ConfigError "<key> must be <allowed>, got <value>"
    (`key` the full key, e.g. "system.refine.m")."""
    if not ok:
        raise ConfigError(f"{key} must be {allowed}, got {value!r}")


def retired_key_message(cls: type, name: str, key: str) -> Optional[str]:
    """The one line for a key `name` (full key `key`) that the dataclass `cls` no longer takes: it
    moved (`MOVED_KEYS` {old: new full key}) or was removed (`REMOVED_KEYS` {old: what to do});
    None for a key it never had."""
    moved = getattr(cls, "MOVED_KEYS", {}).get(name)
    if moved:
        return f"config key '{key}' has moved: use '{moved}'"
    removed = getattr(cls, "REMOVED_KEYS", {}).get(name)
    if removed:
        return f"config key '{key}' was removed: {removed}"
    return None


def _full_key(where: str, e: OmegaConfBaseException) -> str:
    key = getattr(e, "full_key", None) or getattr(e, "key", None)
    key = "" if key is None else str(key)
    return ".".join(k for k in (where, key) if k)


def _first_line(e: OmegaConfBaseException) -> str:
    """OmegaConf messages append 'full_key: ... object_type=...' lines; keep the sentence."""
    msg = getattr(e, "msg", None) or str(e)
    return str(msg).strip().splitlines()[0] if str(msg).strip() else type(e).__name__


def parse_structured(cfg_cls: Type[T], cfg: Any = None, where: str = "", label: str = "") -> T:
    """Merge a plain/OmegaConf mapping into the dataclass `cfg_cls`, rejecting unknown keys.

    A dataclass may name keys that moved elsewhere in a class attribute `MOVED_KEYS`
    ({old key: new full key}) and keys that were removed in `REMOVED_KEYS` ({old key: what to do
    instead}); using one fails with one line that says so.

    `where` names the YAML section (e.g. "system") so errors point at the full key
    (e.g. 'system.geometry.plyy', also inside nested dataclasses). Without it, `label` (e.g. the
    class of a component built outside a config) starts the keys of the messages instead.
    """
    assert is_dataclass(cfg_cls), cfg_cls
    prefix = where or label
    if isinstance(cfg, cfg_cls):
        return cfg
    base = OmegaConf.structured(cfg_cls)
    if cfg is None:
        cfg = {}
    if is_dataclass(cfg):
        cfg = OmegaConf.structured(cfg)
    if not isinstance(cfg, (dict, DictConfig)):
        raise ConfigError(
            f"config section '{prefix or cfg_cls.__qualname__}' must be a mapping of keys to values, "
            f"got {type(cfg).__name__}: {cfg!r}"
        )
    try:
        merged = OmegaConf.merge(base, cfg)
        # Turn into a real dataclass instance (this also resolves ${...} interpolations);
        # nested untyped dicts stay DictConfigs.
        return OmegaConf.to_object(merged)
    except ConfigKeyError as e:
        key = _full_key(prefix, e)
        owner = getattr(e, "object_type", None)
        owner = owner if owner is not None and is_dataclass(owner) else cfg_cls
        retired = retired_key_message(owner, str(e.key), key)
        if retired:
            raise ConfigError(retired) from None
        allowed = [f.name for f in fields(owner)]
        raise ConfigError(unknown_key_message(key, allowed, owner.__qualname__, is_path=bool(where))) from None
    except ValidationError as e:
        key = _full_key(prefix, e)
        if key and key != prefix:
            raise ConfigError(f"bad value for config key '{key}': {_first_line(e)}") from None
        raise ConfigError(f"bad value in config section '{prefix or cfg_cls.__qualname__}': {_first_line(e)}") from None
    except OmegaConfBaseException as e:
        key = _full_key(prefix, e) or cfg_cls.__qualname__
        raise ConfigError(f"config error at '{key}': {_first_line(e)}") from None


def check_saved_config(saved: Any, cls: type, cfg: Any, where: str) -> None:
    """Resuming from a checkpoint whose config (`saved`, the section `where` of the dataclass `cls`,
    `cfg` the config now) holds a retired key: a removed key at another value than the method now
    has (`RETIRED_VALUES` {key: that value}), or a moved key (`MOVED_KEYS` {key: new full key})
    at another value than the new key has now, stops with one line naming it."""
    if not hasattr(saved, "get") or not is_dataclass(cls):
        return
    root = cfg

    def now(full_key: str) -> Any:
        node = root
        for part in full_key.split(".")[1:]:
            if not hasattr(node, part):
                return None
            node = getattr(node, part)
        return node

    def walk(section: Any, owner: type, prefix: str) -> None:
        for key, value in getattr(owner, "RETIRED_VALUES", {}).items():
            old = section.get(key)
            if old is not None and old != value:
                raise ConfigError(f"the checkpoint was written with {prefix}.{key}={old!r}, a setting that was removed "
                                  f"(the method now always runs as with {value!r}): start a new run")
        for key, new in getattr(owner, "MOVED_KEYS", {}).items():
            old, value = section.get(key), now(new)
            if old is not None and value is not None and old != value:
                raise ConfigError(f"the checkpoint was written with {prefix}.{key}={old!r}, which has moved to {new} "
                                  f"(now {value!r}): resume with {new}={old!r} or start a new run")
        for f in fields(owner):
            if is_dataclass(f.type if isinstance(f.type, type) else None) and hasattr(section.get(f.name), "get"):
                walk(section.get(f.name), f.type, f"{prefix}.{f.name}")
            elif f.default_factory is not MISSING and hasattr(section.get(f.name), "get"):
                sub = f.default_factory()
                if is_dataclass(sub):
                    walk(section.get(f.name), type(sub), f"{prefix}.{f.name}")

    walk(saved, cls, where)


def unknown_key_message(key: str, allowed: Collection[str], owner: str, is_path: bool = True) -> str:
    """The error of an unknown `key` (full dotted name): what is allowed, and how to fix it. With
    `is_path` false the key starts with a label, not a config section (no section to clear)."""
    name = key.rsplit(".", 1)[-1]
    allowed = sorted(allowed)
    close = difflib.get_close_matches(name, allowed, n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    msg = f"unknown config key '{key}'{hint} for {owner}; allowed keys: {', '.join(allowed) or '(none)'}"
    section = key.rsplit(".", 1)[0] if "." in key and is_path else ""
    if not section:
        return f"{msg}. Correct or remove the key"
    return (f"{msg}. Correct or remove the key; to replace the whole section from the command line, give "
            f"{section}=null (the YAML's '{section}' keys are dropped, the defaults apply) "
            "followed by the keys you want")


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


# The Config dataclasses a type's section is read with: (type key, e.g. "system.guidance_type",
# its value) -> the classes (one, or several for a choice made later such as `renderer_type:
# auto`), or None when that cannot be told (then the section is left to the type itself).
SectionConfigs = Callable[[str, str], Optional[Sequence[type]]]


def _section_keys(configs: Sequence[type]) -> Tuple[List[str], Dict[str, type]]:
    """(the keys, {retired key: the Config that retired it (MOVED_KEYS, REMOVED_KEYS)}) of the
    Config dataclasses of a section."""
    known = sorted({f.name for c in configs for f in fields(c)})
    retired: Dict[str, type] = {}
    for c in configs:
        retired.update({k: c for k in (*getattr(c, "MOVED_KEYS", {}), *getattr(c, "REMOVED_KEYS", {}))})
    return known, retired


def _leaves(tree: Any, prefix: str = "") -> Dict[str, Any]:
    """{"a.b": value} of the leaves of a nested mapping (an empty mapping is a leaf)."""
    if isinstance(tree, dict) and tree:
        out: Dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: tree}


def _select(cfg: DictConfig, key: str) -> Any:
    return OmegaConf.select(cfg, key, default=None, throw_on_resolution_failure=False)


def _drop(cfg: DictConfig, key: str) -> None:
    parent, _, name = key.rpartition(".")
    node = _select(cfg, parent) if parent else cfg
    if isinstance(node, DictConfig) and name in node:
        del node[name]


def _clear_sections(yaml_cfg: DictConfig, cli: DictConfig, overrides: Sequence[str]) -> List[str]:
    """Apply `section=null` (the YAML's section is dropped, the section is empty unless keys given
    after it fill it) and refuse `section={}` on a non-empty section (merging an empty mapping
    changes nothing: the trap that `null` replaces). Returns the cleared sections."""
    cleared = []
    for item in overrides:
        key = item.split("=", 1)[0].strip()
        value = _select(OmegaConf.from_dotlist([item]), key)
        in_yaml = _select(yaml_cfg, key)
        is_section = isinstance(in_yaml, DictConfig) or _select(yaml_cfg, key + TYPE_SUFFIX) is not None
        if value is None and is_section:
            _drop(yaml_cfg, key)
            if _select(cli, key) is None:  # nothing given after it: an empty section, the defaults
                OmegaConf.update(cli, key, {}, merge=False)
            cleared.append(key)
        elif isinstance(value, DictConfig) and not value and isinstance(in_yaml, DictConfig) and in_yaml:
            raise ConfigError(
                f"override '{item}' changes nothing: command-line values merge into the YAML's '{key}'; "
                f"to clear that section give {key}=null (then the keys you want after it)"
            )
    return cleared


def _type_keys(cfg: DictConfig) -> List[str]:
    """The `*_type` keys of `cfg` whose value is a name, shallowest first (system_type before
    system.guidance_type)."""
    leaves = _leaves(OmegaConf.to_container(cfg, resolve=False))
    keys = [k for k, v in leaves.items() if k.endswith(TYPE_SUFFIX) and isinstance(v, str) and "${" not in v]
    return sorted(keys, key=lambda k: k.count("."))


def _switch_types(yaml_cfg: DictConfig, cli: DictConfig, cleared: Sequence[str],
                  section_configs: SectionConfigs) -> None:
    """For each `*_type` the command line changes, drop the keys of the YAML's section beside it
    that the new type does not take (one log line per section)."""
    for type_key in _type_keys(cli):
        new, old = _select(cli, type_key), _select(yaml_cfg, type_key)
        section = type_key[: -len(TYPE_SUFFIX)]
        if new == old or any(section == c or section.startswith(c + ".") for c in cleared):
            continue
        in_yaml = _select(yaml_cfg, section)
        configs = section_configs(type_key, new) if isinstance(in_yaml, DictConfig) else None
        if configs is None:
            continue
        known, _ = _section_keys(configs)
        dropped = sorted(str(k) for k in in_yaml.keys() if k not in known)
        for k in dropped:
            del in_yaml[k]
        if dropped:
            was = f"the YAML's {old}" if old is not None else "the default type"
            log.info("%s=%s replaces %s: the YAML's %s keys that %s does not take are dropped: %s",
                     type_key, new, was, section, new, ", ".join(dropped))


def _check_type_sections(cfg: DictConfig, section_configs: SectionConfigs) -> None:
    """Every section beside a `*_type` holds only keys its type takes (its top level; the type's
    own parsing checks deeper): a misspelt key fails now, named by its config path, before any
    component is built."""
    for type_key in _type_keys(cfg):
        section = type_key[: -len(TYPE_SUFFIX)]
        name, given = _select(cfg, type_key), _select(cfg, section)
        if not isinstance(given, DictConfig) or not given:
            continue
        configs = section_configs(type_key, name)
        known, retired = _section_keys(configs or ())
        if not known:  # unknown, or a Config without fields: the type's own parsing decides
            continue
        for key in sorted(str(k) for k in given.keys()):
            if key in retired and key not in known:
                raise ConfigError(retired_key_message(retired[key], key, f"{section}.{key}"))
            if key not in known:
                raise ConfigError(unknown_key_message(f"{section}.{key}", known, f"{type_key}={name}"))


def load_config(path: str, overrides: Optional[List[str]] = None,
                section_configs: Optional[SectionConfigs] = None) -> DictConfig:
    """Read a YAML config, apply `key=value` overrides (OmegaConf dotlist) and return it merged
    onto the `ExperimentConfig` defaults with every `${...}` interpolation resolved.

    `section=null` clears a section of the YAML. With `section_configs` (the Config a registered
    type reads its section with), an override that changes a `*_type` drops the keys of the YAML's
    section that the new type does not take (see the module's docstring), and the top level of
    every section beside a `*_type` is checked against its type.

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
    overrides = list(overrides or [])
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override '{item}' is not of the form key=value")
    try:
        cli = OmegaConf.from_dotlist(overrides)
    except Exception as e:
        raise ConfigError(f"bad command-line override: {str(e).splitlines()[0]}") from None
    cleared = _clear_sections(yaml_cfg, cli, overrides)
    if section_configs is not None:
        _switch_types(yaml_cfg, cli, cleared, section_configs)
    try:
        merged = OmegaConf.merge(yaml_cfg, cli)
    except Exception as e:
        raise ConfigError(f"bad command-line override: {str(e).splitlines()[0]}") from None
    try:
        parse_structured(ExperimentConfig, merged, where="")
        if section_configs is not None:
            _check_type_sections(merged, section_configs)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    cfg = OmegaConf.merge(OmegaConf.structured(ExperimentConfig), merged)
    try:
        OmegaConf.resolve(cfg)  # so that sections handed to components stand alone
    except OmegaConfBaseException as e:
        raise ConfigError(f"{path}: config error at '{_full_key('', e)}': {_first_line(e)}") from None
    return cfg
