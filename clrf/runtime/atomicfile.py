"""Replacing a file or a folder so that a reader, or a process killed at any moment, sees the
old one or the new one, never half of one: write under a temporary name in the same folder,
then rename it onto the real name. The only place in clrf that renames a temporary file.

    with atomic_path(out / "frame_000.png") as tmp:   # out/frame_000.png.tmp<pid>-<hex>.png
        imageio.v3.imwrite(tmp, img)                  # the writer creates the file at tmp

A temporary name is ``NAME.tmp<pid>-<hex><ext>``: it keeps the real extension (imageio,
matplotlib and numpy.save pick the format by it) and matches ``*.tmp[0-9]*``, the pattern a run
folder's leftover cleanup removes (clrf/outputs/rundir.py TEMP_PATTERNS).

``sync=True`` (the default) fsyncs the file before the rename and its folder after it, so the
new file also survives a power loss: checkpoints, run files and exports keep it. Caches that are
computed again when lost (jsonfile.py's, the MLP tiling, triangulated points) pass sync=False;
the rename still keeps them whole when the process dies.
"""
from __future__ import annotations

import os
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path


def _temp_name(path: Path, suffix: str | None) -> Path:
    ext = path.suffix if suffix is None else suffix
    return path.with_name(f"{path.name}.tmp{os.getpid()}-{secrets.token_hex(4)}{ext}")


def _fsync_file(path: Path):
    fd = os.open(path, os.O_RDWR if os.name == "nt" else os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path):
    """Make a rename in ``folder`` durable; skipped where folders cannot be fsynced."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove(p: Path):
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


@contextmanager
def atomic_path(path, *, suffix: str | None = None, sync: bool = True):
    """Yield a temporary path beside ``path`` ending with ``suffix`` (default: ``path``'s
    extension); it is not created: the caller writes the file there. On a clean exit the file
    is fsynced (``sync``) and renamed onto ``path``; on an exception (KeyboardInterrupt too) it
    is removed, ``path`` is left as it was and the exception propagates."""
    path = Path(path)
    tmp = _temp_name(path, suffix)
    try:
        yield tmp
        if sync:
            _fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if sync:
        _fsync_dir(path.parent)


def write_text(path, text: str, *, sync: bool = True):
    """Replace ``path`` by ``text`` (UTF-8, written as is: no newline translation)."""
    with atomic_path(path, sync=sync) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)


def write_bytes(path, data: bytes, *, sync: bool = True):
    """Replace ``path`` by ``data``."""
    with atomic_path(path, sync=sync) as tmp:
        tmp.write_bytes(data)


@contextmanager
def atomic_dir(path):
    """The folder counterpart of :func:`atomic_path`: yield a temporary path beside ``path``
    (not created) to build a folder at; on a clean exit it takes the place of ``path``. What was
    at ``path`` is renamed aside first and deleted only once the new folder is in place, so a
    kill leaves the old one (at worst under a ``.tmp`` name beside it) or the new one, never a
    half-deleted one. An exception removes the temporary folder. The folder's files are not
    fsynced (a folder of many files, which its caller can make again)."""
    path = Path(path)
    tmp = _temp_name(path, "")
    old = None
    try:
        yield tmp
        if path.exists() or path.is_symlink():
            old = _temp_name(path, "")
            os.replace(path, old)
        try:
            os.replace(tmp, path)
        except BaseException:
            if old is not None:
                os.replace(old, path)
                old = None
            raise
    except BaseException:
        _remove(tmp)
        raise
    if old is not None:
        _remove(old)
