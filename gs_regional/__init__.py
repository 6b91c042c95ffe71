"""gs_regional: text-driven regional editing of 3D Gaussian Splatting scenes."""
from gs_regional.registry import find, register, registered

__version__ = "0.1.0"

__all__ = ["find", "register", "registered", "GaussianModel", "Camera", "load_cameras", "render", "edit", "load_edit", "EditResult", "localize", "Localized", "load_localized"]

_LAZY = {
    "GaussianModel": ("gs_regional.geometry.gaussian_model", "GaussianModel"),
    "Camera": ("gs_regional.data.cameras", "Camera"),
    "load_cameras": ("gs_regional.api", "load_cameras"),
    "render": ("gs_regional.api", "render"),
    "edit": ("gs_regional.api", "edit"),
    "load_edit": ("gs_regional.api", "load_edit"),
    "EditResult": ("gs_regional.api", "EditResult"),
    "localize": ("gs_regional.api", "localize"),
    "Localized": ("gs_regional.api", "Localized"),
    "load_localized": ("gs_regional.api", "load_localized"),
}


def __getattr__(name):  # PEP 562: keep `import gs_regional` light
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'gs_regional' has no attribute '{name}'")
