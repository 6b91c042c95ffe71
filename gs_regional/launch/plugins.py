"""Plugins: every module `x.py` and package `x/__init__.py` under `custom/` is imported as
`custom.<x>` before the config is read, so that the components it registers can be named in YAML."""
from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import logging
import os
import sys
import traceback
import types
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from gs_regional.registry import note_import_error

log = logging.getLogger(__name__)

PLUGIN_PACKAGE = "custom"  # plugins are imported as custom.<name>, whatever folder they live in


def default_custom_dir() -> Path:
    """`custom/` beside launch.py (the repository root)."""
    return Path(__file__).resolve().parents[2] / "custom"


def _plugin_package(custom_dir: Path) -> types.ModuleType:
    """The package `custom` whose search path is `custom_dir` (created, or reset when the folder
    differs from the one of an earlier call in this process)."""
    folder = str(custom_dir.resolve())
    pkg = sys.modules.get(PLUGIN_PACKAGE)
    if pkg is not None and list(getattr(pkg, "__path__", [])) == [folder]:
        return pkg
    for name in [m for m in sys.modules if m == PLUGIN_PACKAGE or m.startswith(PLUGIN_PACKAGE + ".")]:
        del sys.modules[name]
    spec = importlib.machinery.ModuleSpec(PLUGIN_PACKAGE, None, is_package=True)
    spec.submodule_search_locations = [folder]
    pkg = importlib.util.module_from_spec(spec)
    pkg.__path__ = [folder]
    sys.modules[PLUGIN_PACKAGE] = pkg
    return pkg


def _plugin_entries(custom_dir: Path) -> List[Tuple[str, str]]:
    """(module name, label) of every plugin module `x.py` and package `x/__init__.py`, by name."""
    entries = []
    for entry in sorted(os.listdir(custom_dir)):
        path = custom_dir / entry
        if entry.startswith((".", "_")):
            continue
        if path.is_file() and entry.endswith(".py"):
            entries.append((entry[:-3], f"{custom_dir.name}/{entry}"))
        elif path.is_dir() and (path / "__init__.py").is_file():
            entries.append((entry, f"{custom_dir.name}/{entry}/"))
    return entries


def _describe_import_error(e: BaseException, custom_dir: Path) -> str:
    """'ErrorType: message (file, line N)', the line being the deepest one inside the plugin folder."""
    msg = f"{type(e).__name__}: {e}"
    if isinstance(e, SyntaxError):  # its message already says where
        return msg
    folder = str(custom_dir.resolve())
    where = None
    for frame in traceback.extract_tb(e.__traceback__):
        if os.path.abspath(frame.filename).startswith(folder + os.sep):
            where = f"{os.path.relpath(frame.filename, folder)}, line {frame.lineno}"
    return f"{msg} ({custom_dir.name}/{where})" if where else msg


def load_plugins(custom_dir: Any, debug: bool = False) -> Dict[str, Optional[str]]:
    """Import every plugin under `custom_dir` as `custom.<name>`.

    A missing or empty folder is fine. A plugin that fails to import is logged as an error with
    its name and the error, and remembered by the registry (an unknown-type error then mentions
    it); the other plugins are still imported. Returns {label: None if imported, else the error}.
    """
    custom_dir = Path(custom_dir)
    if not custom_dir.is_dir():
        log.debug("no plugin folder at %s", custom_dir)
        return {}
    _plugin_package(custom_dir)
    importlib.invalidate_caches()  # files may have been written since the last import
    results: Dict[str, Optional[str]] = {}
    for module, label in _plugin_entries(custom_dir):
        full = f"{PLUGIN_PACKAGE}.{module}"
        try:
            importlib.import_module(full)
        except Exception as e:
            # Drop the half-imported module so that a later import tries again.
            for name in [m for m in sys.modules if m == full or m.startswith(full + ".")]:
                del sys.modules[name]
            err = _describe_import_error(e, custom_dir)
            results[label] = err
            note_import_error(f"plugin {label}", err)
            log.error("plugin %s failed to import: %s", label, err)
            if debug:
                log.error("".join(traceback.format_exception(type(e), e, e.__traceback__)))
        else:
            results[label] = None
            note_import_error(f"plugin {label}", None)
            log.debug("loaded plugin %s", label)
    return results
