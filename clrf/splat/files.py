"""Splat files by their ending: the one place that picks the format of a splat file to write
(``clrf export --splats FILE``) or to read (``splat.init_ply``).

  .ply             the 3DGS PLY (ply.py): float32, everything kept (a PLY whose header
                   declares SuperSplat's 'chunk' element is read as a compressed PLY)
  .spz             Niantic's SPZ (spz.py): gzip of quantised attributes, about a tenth of the
                   PLY; SH degree 0-3 kept, quantised
  .glb, .gltf      glTF 2.0 with KHR_gaussian_splatting (gltf.py): float32, binary or JSON
                   with the buffer embedded; everything kept
  .compressed.ply  SuperSplat's compressed PLY (compressed_ply.py): chunks of 256, 16 bytes
                   a Gaussian and one a SH coefficient
  .splat           antimatter15's (antimatter.py): 32 bytes a Gaussian, SH degree 0 only

The longest ending that matches wins (".compressed.ply" before ".ply").

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

from . import antimatter, compressed_ply, gltf, spz
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
    ".glb": Format(gltf.write_gltf, gltf.read_gltf, 3, "glTF binary, KHR_gaussian_splatting"),
    ".gltf": Format(gltf.write_gltf, gltf.read_gltf, 3, "glTF, KHR_gaussian_splatting"),
    ".compressed.ply": Format(compressed_ply.write_compressed_ply,
                              compressed_ply.read_compressed_ply, 3, "SuperSplat compressed PLY"),
    ".splat": Format(antimatter.write_antimatter, antimatter.read_antimatter, 0,
                     "antimatter15 .splat"),
}
SUFFIXES = tuple(FORMATS)


def suffix_list() -> str:
    """'.ply, .spz, ... or .splat' for messages."""
    return ", ".join(SUFFIXES[:-1]) + " or " + SUFFIXES[-1]


def suffix_of(path) -> str | None:
    """The longest of SUFFIXES that the file name ``path`` ends in (any case), or None."""
    name = Path(path).name.lower()
    hits = [s for s in SUFFIXES if name.endswith(s)]
    return max(hits, key=len) if hits else None


def format_of(path) -> Format | None:
    """The Format ``path`` ends in (any case; ".compressed.ply" before ".ply"), or None."""
    s = suffix_of(path)
    return FORMATS[s] if s else None


def write_splat_file(path, means, log_scales, quats, opacity_logits, sh, *,
                     antialiased: bool = False) -> int:
    """Write n splats to ``path`` in the format its ending names (SUFFIXES):
    means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n],
    sh [n, B, 3]. ``antialiased`` (trained with Mip-Splatting's filters) sets SPZ's flag; the
    other formats have none. Returns n; another ending raises ValueError."""
    fmt = format_of(path)
    if fmt is None:
        raise ValueError(f"{path}: a splat file ends in {suffix_list()}")
    kw = {"antialiased": antialiased} if fmt.aa_flag else {}
    return fmt.write(path, means, log_scales, quats, opacity_logits, sh, **kw)


def read_splat_file(path) -> dict:
    """The splats of ``path`` by its ending (SUFFIXES), in clrf's axes: means, log_scales,
    quats, opacity_logits, sh [n, B, 3], names (and the format's own extras). A .ply whose
    header declares a 'chunk' element is read as a compressed PLY (gsplat writes them under
    any name). An unreadable file, or another ending, raises SplatFileError naming the file."""
    s = suffix_of(path)
    if s is None:
        raise SplatFileError(f"{path}: not a splat file name: a splat file ends in "
                             f"{suffix_list()}")
    if s == ".ply" and _declares_chunks(path):
        s = ".compressed.ply"
    return FORMATS[s].read(path)


def _declares_chunks(path) -> bool:
    """Whether the PLY at ``path`` starts with a header declaring a 'chunk' element (False
    where it cannot be read: the PLY reader then says why)."""
    try:
        with open(path, "rb") as fh:
            return compressed_ply.is_compressed(fh.read(1 << 16))
    except OSError:
        return False
