"""Splat files by their ending: the one place that picks the format of a splat file to write
(``clrf export --splats FILE``) or to read (``splat.init_ply``).

  .ply    the 3DGS PLY (ply.py): float32, everything kept
  .spz    Niantic's SPZ (spz.py): gzip of quantised attributes, about a tenth of the PLY; SH
          degree 0-3 kept, quantised
  .splat  antimatter15's (antimatter.py): 32 bytes a Gaussian, SH degree 0 only

Each writer replaces the file atomically (clrf.runtime.atomicfile) and takes the arrays of
n Gaussians in clrf's axes; each reader gives them back in clrf's axes as a dict: means [n, 3],
log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n], sh [n, B, 3], names.

>>> write_splat_file("scene.spz", means, log_scales, quats, opacity_logits, sh)
>>> read_splat_file("scene.spz")["means"]
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from . import antimatter, spz
from .ply import SplatFileError, read_splat_ply, write_splat_ply


@dataclass(frozen=True)
class Format:
    """One splat file format: its writer (path, means, log_scales, quats, opacity_logits, sh)
    -> n, its reader (path) -> dict, the highest SH degree it keeps, one line for messages,
    and whether it records that a model was trained anti-aliased (the writer then takes
    ``antialiased=``)."""
    write: Callable
    read: Callable
    max_degree: int
    title: str
    aa_flag: bool = False


FORMATS = {
    ".ply": Format(write_splat_ply, read_splat_ply, 3, "3DGS PLY"),
    ".spz": Format(spz.write_spz, spz.read_spz, 3, f"SPZ version {spz.WRITE_VERSION}",
                   aa_flag=True),
    ".splat": Format(antimatter.write_antimatter, antimatter.read_antimatter, 0,
                     "antimatter15 .splat"),
}
SUFFIXES = tuple(FORMATS)


def suffix_list() -> str:
    """'.ply, .spz or .splat' for messages."""
    return ", ".join(SUFFIXES[:-1]) + " or " + SUFFIXES[-1]


def format_of(path) -> Format | None:
    """The Format ``path`` ends in (any case), or None."""
    return FORMATS.get(Path(path).suffix.lower())


def write_splat_file(path, means, log_scales, quats, opacity_logits, sh, *,
                     antialiased: bool = False) -> int:
    """Write n splats to ``path`` in the format its ending names (.ply, .spz, .splat):
    means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n],
    sh [n, B, 3]. ``antialiased`` (trained with Mip-Splatting's filters) sets SPZ's flag; the
    other formats have none. Returns n; another ending raises ValueError."""
    fmt = format_of(path)
    if fmt is None:
        raise ValueError(f"{path}: a splat file ends in {suffix_list()}")
    kw = {"antialiased": antialiased} if fmt.aa_flag else {}
    return fmt.write(path, means, log_scales, quats, opacity_logits, sh, **kw)


def read_splat_file(path) -> dict:
    """The splats of ``path`` by its ending (.ply, .spz, .splat), in clrf's axes: means,
    log_scales, quats, opacity_logits, sh [n, B, 3], names (and the format's own extras).
    An unreadable file, or another ending, raises SplatFileError naming the file."""
    fmt = format_of(path)
    if fmt is None:
        raise SplatFileError(f"{path}: not a splat file name: a splat file ends in "
                             f"{suffix_list()}")
    return fmt.read(path)
