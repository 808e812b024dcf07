"""What the commands of the CLI share: the usage error and its exit status, and the errors a
command reports as bad input (one message naming the file or field and the fix, exit 2)."""
from __future__ import annotations

from pathlib import Path

EXIT_USAGE = 2
EXIT_BUG = 1       # clrf's own failure (a bug to report), never the user's input


class CliError(Exception):
    pass


def user_errors() -> tuple:
    """The exceptions the CLI reports as bad input rather than as a crash."""
    from ..data.base import DataError
    from ..interface import InputFileError, StateError, Unsupported
    from ..outputs.camera_path import CameraPathError
    from ..outputs.checkpoint import CheckpointError
    from ..outputs.export import ExportError
    from ..runtime.device import DeviceError
    from ..runtime.programs import BuildError
    from ..training.config import ConfigError
    from ..training.perceptual import LpipsUnavailable
    from ..viewer.core import ViewerError
    return (CliError, ConfigError, DataError, CheckpointError, DeviceError, BuildError,
            ExportError, CameraPathError, LpipsUnavailable, ViewerError, Unsupported, StateError,
            InputFileError)


def out_dir(path) -> Path:
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out}: is an existing file, not a folder; pass a folder path")
    return out
