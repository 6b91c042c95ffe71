"""Name -> class registry used to assemble systems from YAML (`*_type` keys)."""
from __future__ import annotations

import logging
from typing import Callable, Dict, Optional, Type

log = logging.getLogger(__name__)

_REGISTRY: Dict[str, type] = {}
# Modules that failed to import (built-in packages, user plugins) -> "ErrorType: message".
# An unknown-name error mentions them: the missing class may live in one of them.
_IMPORT_ERRORS: Dict[str, str] = {}


class RegistryError(KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _kind(cls: type) -> str:
    """Which kind of component a class is (geometry, renderers, guidance, ...): the package of the
    first class in its MRO that lives in a built-in component package.

    A simulator (gs_regional.sim) or a plugin is of the kind of the interface it implements: the
    simulated editor is a guidance. A plugin class that derives from none of them is "custom"
    (accepted for any kind: nothing tells what it is)."""
    for c in cls.__mro__:
        parts = c.__module__.split(".")
        if len(parts) >= 2 and parts[0] == "gs_regional" and parts[1] in BUILTIN_PACKAGES and parts[1] != "sim":
            return parts[1]
    return "custom"


def register(name: str) -> Callable[[Type], Type]:
    """Class decorator: `@register("gaussian-model")`."""

    def deco(cls: Type) -> Type:
        old = _REGISTRY.get(name)
        # The same class defined again by the same module (the module was executed again, e.g. a
        # plugin re-imported) replaces its old self; any other class is a genuine clash.
        same_origin = old is not None and (old.__module__, old.__qualname__) == (cls.__module__, cls.__qualname__)
        if old is not None and old is not cls and not same_origin:
            raise RegistryError(
                f"name '{name}' is already registered to {old.__module__}.{old.__qualname__}; "
                f"cannot register {cls.__module__}.{cls.__qualname__} under the same name"
            )
        _REGISTRY[name] = cls
        cls.registered_name = name
        return cls

    return deco


def note_import_error(module: str, error: Optional[str]) -> None:
    """Record (or with `error=None` forget) that `module` failed to import."""
    if error is None:
        _IMPORT_ERRORS.pop(module, None)
    else:
        _IMPORT_ERRORS[module] = error


def import_errors() -> Dict[str, str]:
    return dict(_IMPORT_ERRORS)


BUILTIN_PACKAGES = ("geometry", "renderers", "data", "guidance", "depth", "sim", "systems")
_builtins_loaded = False


def load_builtins() -> None:
    """Import every built-in component package so that its classes register themselves.

    A package that fails to import is logged and remembered (unknown-name errors mention it)
    instead of making every lookup fail: components of the other packages stay usable.
    """
    global _builtins_loaded
    if _builtins_loaded:
        return
    import importlib

    for pkg in BUILTIN_PACKAGES:
        module = f"gs_regional.{pkg}"
        try:
            importlib.import_module(module)
        except Exception as e:
            msg = f"{type(e).__name__}: {e}"
            note_import_error(module, msg)
            log.error("built-in package %s failed to import: %s", module, msg)
    _builtins_loaded = True


def find(name: str, kind: str | None = None, key: str | None = None) -> type:
    """Return the class registered as `name`. With `kind`, a class of another kind is refused
    (e.g. a renderer named as the guidance) and the error lists only the names of that kind;
    `key` (e.g. "system.guidance_type") starts the error message."""
    load_builtins()
    where = f"{key}: " if key else ""
    what = f"{kind} " if kind else ""
    names = sorted(n for n, c in _REGISTRY.items() if kind is None or _kind(c) in (kind, "custom"))
    listed = f"registered {what}types: {', '.join(names) or '(none)'}"
    if name in _REGISTRY:
        cls = _REGISTRY[name]
        actual = _kind(cls)
        if kind is None or actual in (kind, "custom"):
            return cls
        raise RegistryError(f"{where}'{name}' is a {actual} component, not a {kind} one; {listed}")
    msg = f"{where}unknown {what}type '{name}'; {listed}"
    if _IMPORT_ERRORS:
        failed = "; ".join(f"{m} ({err})" for m, err in _IMPORT_ERRORS.items())
        msg += f". It may be defined in a module that failed to import: {failed}"
    raise RegistryError(msg)


def registered() -> Dict[str, type]:
    load_builtins()
    return dict(_REGISTRY)
