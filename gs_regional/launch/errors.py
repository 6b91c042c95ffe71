"""Which exceptions are the user's to fix (one line `error: ...`, exit code 2) rather than bugs
(a traceback)."""
from __future__ import annotations

from typing import Tuple, Type

from gs_regional.config import ConfigError
from gs_regional.registry import RegistryError


def input_error_types() -> Tuple[Type[BaseException], ...]:
    """The typed errors of the readers (and of a checkpoint or trial folder the disk refuses): each message
    names the file (or model) at fault."""
    from gs_regional.data.colmap import ColmapError
    from gs_regional.data.images import ImageLoadError
    from gs_regional.data.loaders import CameraLoadError
    from gs_regional.data.nerfstudio import TransformsError
    from gs_regional.data.points import PointsError
    from gs_regional.geometry.ply import PlyError
    from gs_regional.launch.checkpoints import CheckpointError, DiskFullError
    from gs_regional.launch.trial import OutputDirError
    from gs_regional.utils.io import OverwriteError
    from gs_regional.utils.pretrained import PretrainedLoadError

    return (PlyError, ColmapError, TransformsError, CameraLoadError, ImageLoadError, PointsError,
            PretrainedLoadError, OverwriteError, CheckpointError, DiskFullError, OutputDirError)


def is_user_error(e: BaseException) -> bool:
    """Mistakes in the config, the command line or the input files (Lightning's own included,
    e.g. `--validate` with a system that has no validation step), as opposed to bugs."""
    if isinstance(e, (ConfigError, RegistryError)) or isinstance(e, input_error_types()):
        return True
    try:
        from lightning.fabric.utilities.exceptions import MisconfigurationException
    except ImportError:  # pragma: no cover
        return False
    return isinstance(e, MisconfigurationException)
