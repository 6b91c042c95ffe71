"""Name -> class registry used to assemble systems from YAML (`*_type` keys)."""
from __future__ import annotations

from typing import Callable, Dict, Type

_REGISTRY: Dict[str, type] = {}


class RegistryError(KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _kind(cls: type) -> str:
    """Which kind of component a class is, from its module path (geometry, renderers, ...)."""
    parts = cls.__module__.split(".")
    if len(parts) >= 2 and parts[0] == "gs_regional":
        return parts[1]
    return "custom"


def register(name: str) -> Callable[[Type], Type]:
    """Class decorator: `@register("gaussian-model")`."""

    def deco(cls: Type) -> Type:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            old = _REGISTRY[name]
            raise RegistryError(
                f"name '{name}' is already registered to {old.__module__}.{old.__qualname__}; "
                f"cannot register {cls.__module__}.{cls.__qualname__} under the same name"
            )
        _REGISTRY[name] = cls
        cls.registered_name = name
        return cls

    return deco


BUILTIN_PACKAGES = ("geometry", "renderers", "data", "guidance", "depth", "systems")
_builtins_loaded = False


def load_builtins() -> None:
    """Import every built-in component package so that its classes register themselves."""
    global _builtins_loaded
    if _builtins_loaded:
        return
    import importlib

    for pkg in BUILTIN_PACKAGES:
        importlib.import_module(f"gs_regional.{pkg}")
    _builtins_loaded = True


def find(name: str, kind: str | None = None) -> type:
    """Return the class registered as `name`; `kind` only sharpens the error message."""
    load_builtins()
    if name in _REGISTRY:
        return _REGISTRY[name]
    names = sorted(
        n for n, c in _REGISTRY.items() if kind is None or _kind(c) == kind or _kind(c) == "custom"
    )
    what = f"{kind} " if kind else ""
    raise RegistryError(f"unknown {what}type '{name}'; registered: {', '.join(names) or '(none)'}")


def registered() -> Dict[str, type]:
    load_builtins()
    return dict(_REGISTRY)
