"""The stages of the regional edit (DESIGN.md §3) as plain functions; systems call them.

`gs_regional.edit` is also the edit from Python: once this package is imported, the name on
`gs_regional` is this module, so calling it calls gs_regional.api.edit (see its docstring)."""
import sys
import types


class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        from gs_regional.api import edit

        return edit(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
