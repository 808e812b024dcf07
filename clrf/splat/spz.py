"""Gaussian splats as Niantic's SPZ file (github.com/nianticlabs/spz; Scaniverse and many web
viewers read it). clrf's own numpy codec, written from the format's description.

Versions 2 and 3: one gzip stream holding a 16-byte little-endian header (magic 0x5053474e,
"NGSP"; version, count: uint32; SH degree, fractional bits, flags, reserved: uint8; flag 0x1:
trained anti-aliased, viewers apply Mip-Splatting's 2D filter; 0x2: vendor extensions follow
the attributes), then each attribute for every Gaussian in turn:

  positions  3 x 24-bit signed fixed point: step 2^-fractional_bits (12 bits: 1/4096 unit,
             0.24 mm where a unit is a metre), range +-2^23 steps (+-2048 units at 12 bits)
  alphas     uint8 round(255 sigmoid(opacity logit)): opacity in steps of 1/255
  colours    uint8 round(255 (0.15 dc + 0.5)): the DC coefficient in steps of 1/38.25
             (COLOR_SCALE 0.15), range +-3.33
  scales     uint8 round(16 (log scale + 10)): log scales in steps of 1/16, range -10..5.94
  rotations  version 3, "smallest three", 4 bytes: the index of the unit quaternion's largest
             component (made positive) in the top 2 bits, then each other component, x y z w
             order, as a sign bit and 9 bits of |q| / sqrt(1/2); version 2, 3 bytes:
             round(127.5 (q + 1)) of x, y, z with w >= 0 recovered from the unit norm
  sh         the coefficients above degree 0, coefficient-major then R G B: uint8 128 + 128 c,
             range -1..127/128 (1.0 is stored as 255). A writer rounds them to a coarser grid
             of the byte so that gzip packs them tighter: Niantic's library to 5 bits (degree
             1: steps of 1/16) and 4 bits (degrees 2-4: steps of 1/8); clrf to 6 and 5 bits
             (steps of 1/32 and 1/16), which every reader reads alike (SH1_BITS below)

Version 4 (written by default by Niantic's library since its release 3.0.0): a 32-byte header
(the fields above, then numStreams: uint8, tocByteOffset: uint32, 12 reserved bytes), a table of
(compressed, uncompressed) uint64 sizes at tocByteOffset, then each non-empty attribute as its
own zstd frame, in the order above; rotations as version 3.

clrf writes version 3, the newest gzip version, which every SPZ reader reads (Niantic's
library of every release since version 3 and the viewers' own decoders): version 4 needs a
zstd compressor, which neither the Python this project supports nor its dependencies have.
It reads versions 2 and 3, and 4 where a zstd decoder is importable (Python 3.14's
compression.zstd, or the zstandard package). SH degree 4 (Niantic's 3.0) reads with band 4
dropped: clrf renders up to degree 3.

Coordinates: SPZ stores RUB axes (x right, y up, z back: OpenGL, three.js); a 3DGS PLY, and so
clrf's world frame as its PLY export writes it, is RDF (x right, y down, z forward: COLMAP). The
writer turns the scene 180 degrees about x (y and z negated, the quaternion (w, x, -y, -z),
each SH coefficient times the sign its polynomial takes under y, z -> -y, -z), as Niantic's
library packs from RDF, and the reader turns it back: clrf's .spz of a scene is what Niantic's
library makes of clrf's .ply of it loaded as RDF and saved as RUB, the conversion its Python
README shows (its ply_to_spz tool, given no coordinate systems, copies the axes as they are).

Lost on the way: the quantisation above (positions within half a step, opacities within 1/510,
...), values beyond each range (clipped), opacities 0 and 1 (read back as 1/510 and 1 - 1/510,
finite logits), and a zero quaternion (clrf culls such a Gaussian; it is written as the
identity with opacity 0, invisible too). Positions beyond +-2048 units take fewer fractional
bits (the header says how many).

>>> write_spz("scene.spz", means, log_scales, quats, opacity_logits, sh)   # sh [n, B, 3]
>>> read_spz("scene.spz")   # read_splat_ply's dict, plus "version" and "antialiased"
"""
from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path

import numpy as np

from ..runtime.atomicfile import write_bytes
from .ply import SplatFileError, file_bytes, splat_arrays

MAGIC = 0x5053474E                 # b"NGSP" little endian
HEADER = struct.Struct("<IIIBBBB")             # versions 1-3, inside the gzip stream
HEADER_V4 = struct.Struct("<IIIBBBBI12x")      # version 4, in the clear
TOC_ENTRY = struct.Struct("<QQ")
WRITE_VERSION = 3                  # the newest gzip version (see the module docstring)
GZIP_VERSIONS, ZSTD_VERSIONS = (2, 3), (4,)      # the versions read
FRACTIONAL_BITS = 12               # Niantic's choice; fewer only where positions need it
COLOR_SCALE = 0.15                 # colour byte = 255 (COLOR_SCALE dc + 0.5)
SH1_BITS, SH_REST_BITS = 6, 5      # bits kept of the SH bytes, degree 1 and degrees 2+: on a
#                                   lego_400 splat scene (100,001 Gaussians, 40 test views)
#                                   Niantic's 5 and 4 lost 0.43 dB against the PLY at 0.094 of
#                                   its bytes, 6 and 5 lose 0.13 dB at 0.115 (7 and 6: 0.04 dB at
#                                   0.137; the other attributes together 0.01 dB)
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2
SQRT1_2 = np.sqrt(0.5)
ALPHA_EDGE = 0.5 / 255             # opacities read at least this far from 0 and 1
FIX = "export it again with `clrf export --splats FILE.spz`, or pass a .ply or .splat"

# RDF (the PLY's axes) <-> RUB (SPZ's): 180 degrees about x, its own inverse
FLIP = np.array([1.0, -1.0, -1.0])
# the axes each SH basis polynomial above degree 0 is odd in (3DGS order, cl/sh.h):
# degree 1: y, z, x; degree 2: xy, yz, 2zz-xx-yy, xz, xx-yy; degree 3: y(3xx-yy), xyz,
# y(4zz-xx-yy), z(2zz-3xx-3yy), x(4zz-xx-yy), z(xx-yy), x(xx-3yy)
SH_ODD_AXES = ("y", "z", "x", "xy", "yz", "", "xz", "", "y", "xyz", "y", "z", "x", "z", "x")


def sh_signs(flip, n_rest: int) -> np.ndarray:
    """[n_rest] factors of the SH coefficients above degree 0 when the axes are multiplied by
    ``flip`` (+-1 each, x y z): the product of the flips of the axes each polynomial is odd in."""
    f = dict(zip("xyz", flip))
    return np.array([np.prod([f[a] for a in axes]) for axes in SH_ODD_AXES[:n_rest]])


def convert_axes(means, quats, sh_rest, flip=FLIP):
    """(means, quats, sh_rest) with the axes multiplied by ``flip`` (a diagonal +-1 matrix F):
    positions F p, rotations F R F (quaternion vector part det(F) F v), SH coefficients
    [n, B - 1, 3] times their signs. With the default flip, RDF <-> RUB either way."""
    flip = np.asarray(flip, np.float64)
    q = np.array(quats, np.float64)
    q[:, 1:] *= np.prod(flip) * flip
    signs = sh_signs(flip, sh_rest.shape[1])
    return means * flip, q, sh_rest * signs[None, :, None]


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _bytes(x):
    """float64 array -> uint8, rounded to nearest and clipped to 0..255."""
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


# ---- rotations (x y z w order inside SPZ) ---------------------------------------------------
_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])   # [largest] -> 3


def pack_smallest_three(q_xyzw) -> np.ndarray:
    """Unit quaternions [n, 4] (x, y, z, w) -> [n, 4] uint8: the version 3 encoding."""
    q = np.asarray(q_xyzw, np.float64)
    n = len(q)
    largest = np.argmax(np.abs(q), 1)
    q = np.where(q[np.arange(n), largest][:, None] < 0, -q, q)
    comp = largest.astype(np.uint32) << 30
    others = _OTHERS[largest]                                  # [n, 3] ascending
    for j in range(3):
        c = q[np.arange(n), others[:, j]]
        mag = np.minimum(np.floor(511.0 * np.abs(c) / SQRT1_2 + 0.5), 511).astype(np.uint32)
        comp |= (((c < 0).astype(np.uint32) << 9) | mag) << (10 * (2 - j))
    return comp.astype("<u4").view(np.uint8).reshape(n, 4)


def unpack_smallest_three(r) -> np.ndarray:
    """[n, 4] uint8 (version 3) -> unit quaternions [n, 4] (x, y, z, w)."""
    r = np.ascontiguousarray(r, np.uint8)
    n = len(r)
    comp = r.view("<u4").reshape(n).astype(np.uint32)
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((n, 4))
    others = _OTHERS[largest]
    for j in range(3):
        field = (comp >> (10 * (2 - j))) & 0x3FF
        v = SQRT1_2 * (field & 0x1FF) / 511.0
        q[np.arange(n), others[:, j]] = np.where(field >> 9, -v, v)
    q[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, 1)))
    return q


def pack_first_three(q_xyzw) -> np.ndarray:
    """Unit quaternions [n, 4] (x, y, z, w) -> [n, 3] uint8: the version 2 encoding."""
    q = np.asarray(q_xyzw, np.float64)
    q = np.where(q[:, 3:] < 0, -q, q)
    return _bytes(127.5 * q[:, :3] + 127.5)


def unpack_first_three(r) -> np.ndarray:
    """[n, 3] uint8 (version 2) -> unit quaternions [n, 4] (x, y, z, w), w >= 0."""
    xyz = np.asarray(r, np.float64) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, 1)))
    return np.concatenate([xyz, w[:, None]], 1)


# ---- SH -------------------------------------------------------------------------------------
def sh_buckets(n_rest: int) -> np.ndarray:
    """[n_rest] grid spacing of each coefficient's byte: 2^(8 - bits)."""
    b = np.full(n_rest, 1 << (8 - SH_REST_BITS))
    b[:3] = 1 << (8 - SH1_BITS)
    return b


def pack_sh(rest) -> np.ndarray:
    """SH coefficients above degree 0 [n, B - 1, 3] -> [n, (B - 1) * 3] uint8: the nearest
    point of the coefficient's grid, the grid's 256 (1.0) clipped to 255 (127/128)."""
    bucket = sh_buckets(rest.shape[1])[None, :, None]
    q = np.round(rest * 128.0 / bucket) * bucket + 128
    return np.clip(q, 0, 255).astype(np.uint8).reshape(len(rest), 3 * rest.shape[1])


# ---- writing --------------------------------------------------------------------------------
def fractional_bits(means) -> int:
    """The most fractional bits (at most FRACTIONAL_BITS) that keep every position within
    24-bit fixed point; ValueError where none do."""
    top = float(np.max(np.abs(means))) if means.size else 0.0
    for bits in range(FRACTIONAL_BITS, -1, -1):
        if round(top * (1 << bits)) < (1 << 23):
            return bits
    raise ValueError(f"positions reach {top:g}: SPZ's 24-bit fixed point holds at most "
                     f"{(1 << 23) - 1}")


def pack(a: dict, version: int = WRITE_VERSION, antialiased: bool = False) -> bytes:
    """The uncompressed version 2 or 3 payload (header and attributes) of splat_arrays ``a``,
    converted to SPZ's RUB axes."""
    n, B = a["sh"].shape[:2]
    norm = np.linalg.norm(a["quats"], axis=1)
    zero = norm == 0      # culled by clrf: the identity, fully transparent
    q = np.where(zero[:, None], [1.0, 0, 0, 0], a["quats"] / np.where(zero, 1, norm)[:, None])
    means, q, rest = convert_axes(a["means"], q, a["sh"][:, 1:])
    bits = fractional_bits(means)
    fixed = np.round(means * (1 << bits)).astype("<i4")
    positions = fixed.view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    alphas = np.where(zero, 0, _bytes(255.0 * _sigmoid(a["opacity_logits"])))
    colours = _bytes(255.0 * (COLOR_SCALE * a["sh"][:, 0] + 0.5))
    scales = _bytes(16.0 * (a["log_scales"] + 10.0))
    xyzw = q[:, [1, 2, 3, 0]]
    rot = pack_smallest_three(xyzw) if version >= 3 else pack_first_three(xyzw)
    degree = int(round(B ** 0.5)) - 1
    flags = FLAG_ANTIALIASED if antialiased else 0
    head = HEADER.pack(MAGIC, version, n, degree, bits, flags, 0)
    parts = [positions, alphas, colours, scales, rot, pack_sh(rest)]
    return head + b"".join(np.ascontiguousarray(p, np.uint8).tobytes() for p in parts)


def write_spz(path, means, log_scales, quats, opacity_logits, sh, *, version=WRITE_VERSION,
              antialiased=False) -> int:
    """Write n splats to ``path`` as SPZ ``version`` (3, or 2 for old readers), atomically:
    means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n],
    sh [n, B, 3] (B = 1, 4, 9, 16), all in clrf's (the PLY's) axes; ``antialiased`` sets the
    header's flag. Returns n."""
    if version not in (2, 3):
        raise ValueError(f"SPZ version {version}: clrf writes versions 2 and 3")
    a = splat_arrays(means, log_scales, quats, opacity_logits, sh)
    payload = pack(a, version, antialiased)
    write_bytes(path, gzip.compress(payload, compresslevel=6, mtime=0))
    return len(a["means"])


# ---- reading --------------------------------------------------------------------------------
def read_spz(path) -> dict:
    """The splats of SPZ file ``path`` in clrf's axes: read_splat_ply's dict (means, log_scales,
    quats (w, x, y, z, unit), opacity_logits, sh [n, B, 3], names: the attribute streams) plus
    ``version`` and ``antialiased``. Anything unreadable raises SplatFileError naming the file
    and what is wrong."""
    path = Path(path)
    data = file_bytes(path, "an SPZ file")
    if data[:2] == b"\x1f\x8b":
        payload = _gunzip(path, data)
        head, streams = _split_gzip_payload(path, payload)
    elif data[:4] == struct.pack("<I", MAGIC):
        head, streams = _split_v4(path, data)
    else:
        raise SplatFileError(f"{path}: not an SPZ file (neither a gzip stream nor an NGSP "
                             f"version 4 header: the file starts {data[:4].hex()}); {FIX}")
    return _unpack(head, streams)


def _gunzip(path, data: bytes) -> bytes:
    try:
        return gzip.decompress(data)
    except EOFError:
        raise SplatFileError(f"{path}: cut short: the gzip stream ends before its end marker "
                             f"({len(data)} bytes); {FIX}") from None
    except (OSError, zlib.error) as e:
        raise SplatFileError(f"{path}: the gzip stream is corrupt ({e}); {FIX}") from None


def _check_header(path, magic, version, degree, bits, gzip_stream: bool):
    """Raise SplatFileError where a header cannot be read (wrong magic, version, degree)."""
    if magic != MAGIC:
        raise SplatFileError(f"{path}: wrong magic 0x{magic:08x} (an SPZ file starts with "
                             f"0x{MAGIC:08x}, 'NGSP'); {FIX}")
    known = GZIP_VERSIONS if gzip_stream else ZSTD_VERSIONS
    if version not in known:
        raise SplatFileError(f"{path}: SPZ version {version} in a "
                             f"{'gzip' if gzip_stream else 'zstd'} file is not one clrf reads "
                             f"(versions 2 and 3 in gzip, 4 in zstd streams); {FIX}")
    if degree > 4:
        raise SplatFileError(f"{path}: SH degree {degree}: SPZ holds degrees 0 to 4; {FIX}")
    if bits > 23:
        raise SplatFileError(f"{path}: {bits} fractional bits: 24-bit positions hold at most "
                             f"23; {FIX}")


def stream_sizes(n: int, degree: int, version: int) -> list:
    """The byte sizes of the six attribute streams (positions, alphas, colours, scales,
    rotations, sh) of n Gaussians."""
    return [9 * n, n, 3 * n, 3 * n, (4 if version >= 3 else 3) * n,
            3 * ((degree + 1) ** 2 - 1) * n]


def _split_gzip_payload(path, payload: bytes):
    if len(payload) < HEADER.size:
        raise SplatFileError(f"{path}: cut short: {len(payload)} bytes, less than the "
                             f"{HEADER.size}-byte header; {FIX}")
    magic, version, n, degree, bits, flags, _ = HEADER.unpack_from(payload)
    _check_header(path, magic, version, degree, bits, gzip_stream=True)
    sizes = stream_sizes(n, degree, version)
    need, have = HEADER.size + sum(sizes), len(payload)
    if have < need or (have > need and not flags & FLAG_EXTENSIONS):
        raise SplatFileError(
            f"{path}: {'cut short' if have < need else 'the count does not match'}: the header "
            f"says {n} Gaussians (SH degree {degree}, {need} bytes), the stream holds {have} "
            f"bytes; {FIX}")
    streams, at = [], HEADER.size
    for s in sizes:
        streams.append(np.frombuffer(payload, np.uint8, s, at))
        at += s
    return (version, n, degree, bits, flags), streams


def _zstd_decompress(blob: bytes, size: int) -> bytes:
    """One zstd frame decoded (``size`` bytes expected) by whichever decoder is importable;
    ImportError where none is."""
    try:
        from compression import zstd          # Python 3.14
        return zstd.decompress(blob)
    except ImportError:
        import zstandard                       # raises ImportError where absent too
        return zstandard.ZstdDecompressor().decompress(blob, max_output_size=size)


def _split_v4(path, data: bytes):
    if len(data) < HEADER_V4.size:
        raise SplatFileError(f"{path}: cut short: {len(data)} bytes, less than the "
                             f"{HEADER_V4.size}-byte header; {FIX}")
    magic, version, n, degree, bits, flags, n_streams, toc = HEADER_V4.unpack_from(data)
    _check_header(path, magic, version, degree, bits, gzip_stream=False)
    sizes = stream_sizes(n, degree, version)
    want = [s for s in sizes if s]
    if n_streams != len(want) or toc < HEADER_V4.size:
        raise SplatFileError(f"{path}: the count does not match: {n} Gaussians of SH degree "
                             f"{degree} need {len(want)} streams, the header lists {n_streams} "
                             f"(table at byte {toc}); {FIX}")
    at = toc + n_streams * TOC_ENTRY.size
    if at > len(data):
        raise SplatFileError(f"{path}: cut short: the stream table ends at byte {at}, the file "
                             f"has {len(data)}; {FIX}")
    table = [TOC_ENTRY.unpack_from(data, toc + i * TOC_ENTRY.size) for i in range(n_streams)]
    listed, end = [u for _, u in table], at + sum(c for c, _ in table)
    if listed != want or end != len(data):
        what = "cut short" if end > len(data) else "the count does not match"
        raise SplatFileError(f"{path}: {what}: {n} Gaussians of SH degree {degree} need "
                             f"streams of {want} bytes, the table lists {listed} ({end} bytes "
                             f"in all, the file has {len(data)}); {FIX}")
    streams = []
    for (c, u) in table:
        try:
            raw = _zstd_decompress(data[at:at + c], u)
        except ImportError:
            raise SplatFileError(f"{path}: SPZ version 4 (zstd streams) needs a zstd decoder: "
                                 f"`pip install zstandard`, or save the file as version 3 "
                                 f"(Niantic's library: PackOptions version=3)") from None
        except Exception as e:                    # the decoders' own error classes
            raise SplatFileError(f"{path}: a zstd stream is corrupt ({e}); {FIX}") from None
        if len(raw) != u:
            raise SplatFileError(f"{path}: a zstd stream holds {len(raw)} bytes, the table "
                                 f"says {u}; {FIX}")
        streams.append(np.frombuffer(raw, np.uint8))
        at += c
    if not sizes[-1]:
        streams.append(np.zeros(0, np.uint8))
    return (version, n, degree, bits, flags), streams


def _unpack(head, streams) -> dict:
    """The read dict of a header (version, n, degree, bits, flags) and its six streams."""
    version, n, degree, bits, flags = head
    pos, alphas, colours, scales, rot, sh = streams
    p = pos.reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    means = ((fixed ^ 0x800000) - 0x800000) / float(1 << bits)
    alpha = np.clip(alphas / 255.0, ALPHA_EDGE, 1.0 - ALPHA_EDGE)
    dc = (colours.reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = scales.reshape(n, 3) / 16.0 - 10.0
    q = (unpack_smallest_three(rot.reshape(n, 4)) if version >= 3
         else unpack_first_three(rot.reshape(n, 3)))[:, [3, 0, 1, 2]]
    q /= np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    dim = (degree + 1) ** 2 - 1
    rest = ((sh.reshape(n, dim, 3).astype(np.float64) - 128.0) / 128.0)[:, :15]   # <= degree 3
    means, q, rest = convert_axes(means, q, rest)
    f32 = np.float32
    return {"means": means.astype(f32), "log_scales": log_scales.astype(f32),
            "quats": q.astype(f32), "opacity_logits": np.log(alpha / (1 - alpha)).astype(f32),
            "sh": np.concatenate([dc[:, None], rest], 1).astype(f32),
            "names": ["positions", "alphas", "colors", "scales", "rotations", "sh"],
            "version": version, "antialiased": bool(flags & FLAG_ANTIALIASED)}
