"""Gaussian splats as the compressed PLY of PlayCanvas's SuperSplat (``.compressed.ply``; its
engine and splat-transform read it, gsplat's exporter writes it as "ply_compressed").

A PLY file, binary little endian, of two or three elements:

  chunk   one per 256 Gaussians (the last one partial), float32: min_x min_y min_z max_x max_y
          max_z (the chunk's positions), min_scale_x .. max_scale_z (its log scales, each bound
          clamped to +-20), and optionally min_r min_g min_b max_r max_g max_b (its colours
          0.5 + SH_C0 dc; without them the colour bytes are the colours themselves)
  vertex  uint32 packed_position, packed_rotation, packed_scale, packed_color:
            position  x, y, z as 11, 10, 11 bits (x in the top bits) of (v - min) / (max - min)
            scale     the log scales the same way over the chunk's scale bounds
            rotation  2 bits: the index (w x y z order, as rot_0..3) of the unit quaternion's
                      largest component, made positive; then the other three in order, 10 bits
                      each of c sqrt(1/2) + 0.5 (c in +-sqrt(1/2))
            color     R, G, B (top byte first) over the chunk's colour bounds, then the opacity
                      after the sigmoid, 8 bits each
          each value v in 0..1 stored as round(v (2^bits - 1))
  sh      (SH degree 1-3) uint8 f_rest_0 .. f_rest_{3(B-1)-1}, channel-major as in the 3DGS
          PLY, each trunc(256 (c / 8 + 0.5)) clipped to 0..255: c in -4..4 in steps of 1/32;
          read back as the middle of its step, byte 0 as -4 and 255 as 4 (PlayCanvas's decoder)

Gaussians are written in Morton order of their positions (10 bits an axis over the scene's
box, as SuperSplat and gsplat order them), so that a chunk's box is small; read back, they
come in that order. The file keeps the PLY's axes (no conversion).

Lost on the way (bounds from the bit widths): positions within half a step of their chunk's
extent, 1 / (2 (2^11 - 1)) of it along x and z, 1 / (2 (2^10 - 1)) along y; log scales the
same over the chunk's log-scale range (values beyond +-20 clipped); the colour within
1 / 510 of the chunk's colour range; opacities within 1 / 510 (0 and 1 read back as 1/510 and
1 - 1/510, finite logits); each stored rotation component within sqrt(2) / (2 (2^10 - 1)); SH
within 1/64 inside -4 + 1/32 .. 4 - 1/32, within 1/32 in the end steps, clipped beyond.
A zero quaternion (a Gaussian clrf culls) is written as the identity with opacity 0.

The reader takes the 12- and 18-property chunk layouts and SH degrees 0-3 (degree 0 with no
sh element, or, as gsplat writes it, an sh element of no properties), from any writer; a
file that is not this layout (a chunk count that is not ceil(n / 256), property types other
than float32 / uint32 / uint8, a missing property) is refused with one message naming the
file and the element or property.

>>> write_compressed_ply("scene.compressed.ply", means, log_scales, quats, opacity_logits, sh)
>>> read_compressed_ply("scene.compressed.ply")   # read_splat_ply's dict, in file order
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..runtime.atomicfile import write_bytes
from .ply import SplatFileError, file_bytes, splat_arrays

CHUNK = 256                        # Gaussians a chunk
SH_C0 = 0.28209479177387814        # the degree-0 SH basis constant
SCALE_CLAMP = 20.0                 # a chunk's log-scale bounds are clamped to +-20
SH_SCALE = 8.0                     # SH byte = trunc(256 (c / 8 + 0.5)): c in -4..4
ROT_SCALE = np.sqrt(0.5)           # rotation component c stored as c sqrt(1/2) + 0.5
POS_BITS = (11, 10, 11)            # packed_position and packed_scale: x, y, z
ALPHA_EDGE = 0.5 / 255             # opacities read at least this far from 0 and 1
CHUNK_PROPS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z",
               "min_scale_x", "min_scale_y", "min_scale_z",
               "max_scale_x", "max_scale_y", "max_scale_z"]
COLOR_PROPS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
VERTEX_PROPS = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4",
             "uint": "<u4", "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1",
             "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
             "float32": "<f4", "float64": "<f8"}
FIX = ("export it again with `clrf export --splats FILE.compressed.ply`, or pass a .ply or "
       ".spz")


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def morton_order(means) -> np.ndarray:
    """[n] indices of positions [n, 3] in Morton (Z-curve) order: each axis as 10 bits over
    the box of all positions, the bits interleaved x lowest; ties in index order."""
    m = np.asarray(means, np.float64)
    if not len(m):
        return np.zeros(0, np.int64)
    lo, extent = m.min(0), np.ptp(m, 0)
    cells = np.floor((m - lo) / np.where(extent > 0, extent, 1.0) * 1024)
    cells = np.clip(cells, 0, 1023).astype(np.uint64)
    code = np.zeros(len(m), np.uint64)
    for bit in range(10):
        for axis in range(3):
            one = (cells[:, axis] >> np.uint64(bit)) & np.uint64(1)
            code |= one << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def pack_unorm(u, bits: int) -> np.ndarray:
    """Values in 0..1 -> round(u (2^bits - 1)), clipped, as uint32."""
    top = (1 << bits) - 1
    return np.clip(np.floor(np.asarray(u) * top + 0.5), 0, top).astype(np.uint32)


def unpack_unorm(packed, shift: int, bits: int) -> np.ndarray:
    """The field of ``bits`` bits at ``shift`` of uint32 ``packed``, as a value in 0..1."""
    top = (1 << bits) - 1
    return ((np.asarray(packed, np.uint32) >> np.uint32(shift)) & np.uint32(top)) / top


def _normalise(v, lo, hi):
    """(v - lo) / (hi - lo) per chunk ([c, 256, k] against [c, 1, k]), 0 where hi == lo."""
    span = hi - lo
    return np.where(span > 0, (v - lo) / np.where(span > 0, span, 1.0), 0.0)


def pack_111011(u) -> np.ndarray:
    """[..., 3] values in 0..1 -> uint32 x:11 | y:10 | z:11 (x in the top bits)."""
    return ((pack_unorm(u[..., 0], 11) << np.uint32(21)) | (pack_unorm(u[..., 1], 10)
            << np.uint32(11)) | pack_unorm(u[..., 2], 11))


def unpack_111011(packed) -> np.ndarray:
    """uint32 [...] -> [..., 3] values in 0..1."""
    return np.stack([unpack_unorm(packed, 21, 11), unpack_unorm(packed, 11, 10),
                     unpack_unorm(packed, 0, 11)], -1)


_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])   # [largest] -> 3


def pack_rotation(q) -> np.ndarray:
    """Unit quaternions [n, 4] (w, x, y, z) -> uint32: the largest component's index in the
    top 2 bits, the other three (largest made positive) as 10 bits each, in order."""
    q = np.asarray(q, np.float64)
    rows = np.arange(len(q))
    largest = np.argmax(np.abs(q), 1)
    q = np.where(q[rows, largest][:, None] < 0, -q, q)
    out = largest.astype(np.uint32) << np.uint32(30)
    for j in range(3):
        c = q[rows, _OTHERS[largest, j]]
        out |= pack_unorm(c * ROT_SCALE + 0.5, 10) << np.uint32(10 * (2 - j))
    return out


def unpack_rotation(packed) -> np.ndarray:
    """uint32 [n] -> unit quaternions [n, 4] (w, x, y, z), the largest from the unit norm."""
    packed = np.asarray(packed, np.uint32)
    rows = np.arange(len(packed))
    largest = (packed >> np.uint32(30)).astype(np.int64)
    q = np.zeros((len(packed), 4))
    for j in range(3):
        q[rows, _OTHERS[largest, j]] = (unpack_unorm(packed, 10 * (2 - j), 10) - 0.5) / ROT_SCALE
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, 1)))
    return q


def sh_bytes(rest) -> np.ndarray:
    """SH coefficients -> uint8 trunc(256 (c / 8 + 0.5)), clipped to 0..255."""
    return np.clip(np.floor(256.0 * (np.asarray(rest) / SH_SCALE + 0.5)), 0, 255).astype(np.uint8)


def sh_values(b) -> np.ndarray:
    """uint8 -> SH coefficients: the middle of the byte's step, 0 -> -4 and 255 -> 4."""
    b = np.asarray(b, np.float64)
    u = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256.0))
    return (u - 0.5) * SH_SCALE


# ---- writing --------------------------------------------------------------------------------
def _chunked(v, n_chunks):
    """[n, ...] -> [n_chunks, 256, ...], the last chunk filled up with its last row."""
    pad = n_chunks * CHUNK - len(v)
    v = np.concatenate([v, np.repeat(v[-1:], pad, 0)]) if pad else v
    return v.reshape((n_chunks, CHUNK) + v.shape[1:])


def pack(a: dict) -> bytes:
    """The compressed PLY file (header and data) of splat_arrays ``a``."""
    n, B = a["sh"].shape[:2]
    order = morton_order(a["means"])
    norm = np.linalg.norm(a["quats"], axis=1)
    zero = norm == 0      # culled by clrf: the identity, fully transparent
    q = np.where(zero[:, None], [1.0, 0, 0, 0], a["quats"] / np.where(zero, 1, norm)[:, None])
    alpha = np.where(zero, 0.0, _sigmoid(a["opacity_logits"]))
    n_chunks = -(-n // CHUNK)
    f32 = np.float32
    vertex = np.zeros((n, 4), "<u4")
    chunk = np.zeros((n_chunks, 18), "<f4")
    if n:
        pos = _chunked(a["means"][order], n_chunks)
        scl = _chunked(a["log_scales"][order], n_chunks)
        rgb = _chunked(0.5 + SH_C0 * a["sh"][order, 0], n_chunks)
        # the bounds as the file keeps them (float32), so that a value decodes where it was put
        bounds = []
        for v, clamp in ((pos, None), (scl, SCALE_CLAMP), (rgb, None)):
            lo, hi = v.min(1).astype(f32), v.max(1).astype(f32)
            if clamp:
                lo, hi = np.clip(lo, -clamp, clamp), np.clip(hi, -clamp, clamp)
            bounds.append((lo.astype(np.float64)[:, None], hi.astype(np.float64)[:, None]))
            chunk[:, len(bounds) * 6 - 6:len(bounds) * 6] = np.concatenate([lo, hi], 1)
        (plo, phi), (slo, shi), (clo, chi) = bounds
        packed_colour = pack_unorm(_normalise(rgb, clo, chi), 8)
        packed_alpha = pack_unorm(_chunked(alpha[order], n_chunks), 8)
        vertex[:, 0] = pack_111011(_normalise(pos, plo, phi)).reshape(-1)[:n]
        vertex[:, 1] = pack_rotation(q[order])
        vertex[:, 2] = pack_111011(_normalise(scl, slo, shi)).reshape(-1)[:n]
        vertex[:, 3] = ((packed_colour[..., 0] << np.uint32(24))
                        | (packed_colour[..., 1] << np.uint32(16))
                        | (packed_colour[..., 2] << np.uint32(8)) | packed_alpha).reshape(-1)[:n]
    # channel-major: f_rest_{c * (B - 1) + (b - 1)} is basis b of channel c
    rest = np.transpose(a["sh"][order, 1:, :], (0, 2, 1)).reshape(n, 3 * (B - 1))
    header = ["ply", "format binary_little_endian 1.0", f"element chunk {n_chunks}"]
    header += [f"property float {k}" for k in CHUNK_PROPS + COLOR_PROPS]
    header += [f"element vertex {n}"] + [f"property uint {k}" for k in VERTEX_PROPS]
    if B > 1:
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (B - 1))]
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii") + b"".join(
        np.ascontiguousarray(x).tobytes() for x in (chunk, vertex, sh_bytes(rest)))


def write_compressed_ply(path, means, log_scales, quats, opacity_logits, sh) -> int:
    """Write n splats to ``path`` as a compressed PLY, atomically: means [n, 3], log_scales
    [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n], sh [n, B, 3] (B = 1, 4, 9, 16), in
    clrf's (the PLY's) axes. Returns n."""
    a = splat_arrays(means, log_scales, quats, opacity_logits, sh)
    write_bytes(path, pack(a))
    return len(a["means"])


# ---- reading --------------------------------------------------------------------------------
def parse_header(path, data: bytes) -> tuple[list, int]:
    """([(element name, count, numpy record dtype)] in file order, the data's first byte) of
    a binary little-endian PLY; SplatFileError where the header cannot be read."""
    end = data.find(b"end_header\n", 0, 1 << 16)
    if not data.startswith(b"ply\n") or end < 0:
        raise SplatFileError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header); {FIX}")
    elements = []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if parts[1:2] != ["binary_little_endian"]:
                raise SplatFileError(f"{path}: format {' '.join(parts[1:])}: a compressed PLY "
                                     f"is binary_little_endian; {FIX}")
        elif parts[0] == "element":
            try:
                elements.append((parts[1], int(parts[2]), []))
            except (IndexError, ValueError):
                raise SplatFileError(f"{path}: bad line {line!r}: expected 'element NAME "
                                     f"COUNT'; {FIX}") from None
        elif parts[0] == "property" and elements:
            if len(parts) != 3 or parts[1] not in PLY_TYPES:
                raise SplatFileError(f"{path}: element {elements[-1][0]}: property "
                                     f"{' '.join(parts[1:])} is not a scalar PLY property; {FIX}")
            elements[-1][2].append((parts[2], PLY_TYPES[parts[1]]))
        else:
            raise SplatFileError(f"{path}: bad header line {line!r}; {FIX}")
    return [(name, count, np.dtype(props)) for name, count, props in elements], \
        end + len(b"end_header\n")


def _require(path, element: str, dtype, names, kind: str):
    """Raise SplatFileError unless ``dtype`` has each of ``names`` as numpy type ``kind``."""
    missing = [k for k in names if k not in dtype.names]
    if missing:
        raise SplatFileError(f"{path}: {element} properties {', '.join(missing)} missing (a "
                             f"compressed PLY's {element} has {' '.join(names)}); {FIX}")
    wrong = [k for k in names if dtype[k] != np.dtype(kind)]
    if wrong:
        raise SplatFileError(f"{path}: {element} property {wrong[0]} is {dtype[wrong[0]]}, "
                             f"expected {np.dtype(kind)}; {FIX}")


def is_compressed(data: bytes) -> bool:
    """Whether a PLY's header (the first bytes of the file) declares a 'chunk' element."""
    end = data.find(b"end_header", 0, 1 << 16)
    return end > 0 and b"\nelement chunk " in data[:end]


def read_compressed_ply(path) -> dict:
    """The splats of compressed PLY ``path`` in file order: read_splat_ply's dict (means,
    log_scales, quats (w, x, y, z, unit), opacity_logits, sh [n, B, 3], names: the vertex and
    sh properties). Anything unreadable raises SplatFileError naming the file and the element
    or property."""
    path = Path(path)
    data = file_bytes(path, "a compressed PLY")
    elements, at = parse_header(path, data)
    found = {name: (count, dtype) for name, count, dtype in elements}
    for name in ("chunk", "vertex"):
        if name not in found:
            raise SplatFileError(f"{path}: no '{name}' element: not a compressed PLY (elements "
                                 f"{', '.join(found) or 'none'}); {FIX}")
    extra = [k for k in found if k not in ("chunk", "vertex", "sh")]
    if extra:
        raise SplatFileError(f"{path}: element {extra[0]!r}: a compressed PLY has chunk, "
                             f"vertex and sh elements only; {FIX}")
    (n_chunks, cdt), (n, vdt) = found["chunk"], found["vertex"]
    has_colour = "min_r" in cdt.names
    _require(path, "chunk", cdt, CHUNK_PROPS + (COLOR_PROPS if has_colour else []), "<f4")
    _require(path, "vertex", vdt, VERTEX_PROPS, "<u4")
    if n_chunks != -(-n // CHUNK):
        raise SplatFileError(f"{path}: the count does not match: {n} vertices need "
                             f"{-(-n // CHUNK)} chunks of {CHUNK}, the header has {n_chunks}; "
                             f"{FIX}")
    n_rest, sdt = 0, None
    if "sh" in found:
        n_sh, sdt = found["sh"]
        n_rest = len(sdt.names)
        if n_rest not in (0, 9, 24, 45):
            raise SplatFileError(f"{path}: {n_rest} sh properties: expected 9, 24 or 45 "
                                 f"(f_rest_*, SH degree 1..3), or none; {FIX}")
        _require(path, "sh", sdt, [f"f_rest_{i}" for i in range(n_rest)], "u1")
        if n_sh != n:
            raise SplatFileError(f"{path}: the count does not match: {n_sh} sh rows for {n} "
                                 f"vertices; {FIX}")
    arrays = {}
    for name, count, dtype in elements:
        if at + count * dtype.itemsize > len(data):
            raise SplatFileError(f"{path}: cut short: element {name} ({count} x "
                                 f"{dtype.itemsize} bytes) needs bytes {at}.."
                                 f"{at + count * dtype.itemsize}, the file has {len(data)}; {FIX}")
        arrays[name] = np.frombuffer(data, dtype, count, at)
        at += count * dtype.itemsize
    chunk = arrays["chunk"]
    props = CHUNK_PROPS + (COLOR_PROPS if has_colour else [])
    for k in props:
        bad = np.flatnonzero(~np.isfinite(chunk[k]))
        if bad.size:
            raise SplatFileError(f"{path}: chunk property {k} of chunk {int(bad[0])} is "
                                 f"{float(chunk[k][bad[0]])} ({bad.size} such chunks): every "
                                 f"value must be finite; {FIX}")
    return unpack(arrays["vertex"], chunk, arrays.get("sh"), has_colour, n_rest,
                  list(vdt.names) + (list(sdt.names) if sdt is not None else []))


def unpack(vertex, chunk, sh, has_colour: bool, n_rest: int, names: list) -> dict:
    """The read dict of the vertex, chunk and sh (or None) records."""
    n = len(vertex)
    c = np.arange(n) // CHUNK

    def bounds(keys):
        return np.stack([chunk[k] for k in keys], 1).astype(np.float64)[c]

    def lerp(lo, hi, t):
        return lo * (1.0 - t) + hi * t

    means = lerp(bounds(CHUNK_PROPS[0:3]), bounds(CHUNK_PROPS[3:6]),
                 unpack_111011(vertex["packed_position"]))
    log_scales = lerp(bounds(CHUNK_PROPS[6:9]), bounds(CHUNK_PROPS[9:12]),
                      unpack_111011(vertex["packed_scale"]))
    col = vertex["packed_color"]
    rgb = np.stack([unpack_unorm(col, s, 8) for s in (24, 16, 8)], 1)
    if has_colour:
        rgb = lerp(bounds(COLOR_PROPS[0:3]), bounds(COLOR_PROPS[3:6]), rgb)
    alpha = np.clip(unpack_unorm(col, 0, 8), ALPHA_EDGE, 1.0 - ALPHA_EDGE)
    B = 1 + n_rest // 3
    shs = np.zeros((n, B, 3))
    shs[:, 0] = (rgb - 0.5) / SH_C0
    if n_rest:
        rest = sh_values(np.stack([sh[f"f_rest_{i}"] for i in range(n_rest)], 1))
        shs[:, 1:] = np.transpose(rest.reshape(n, 3, B - 1), (0, 2, 1))
    f32 = np.float32
    return {"means": means.astype(f32), "log_scales": log_scales.astype(f32),
            "quats": unpack_rotation(vertex["packed_rotation"]).astype(f32),
            "opacity_logits": np.log(alpha / (1.0 - alpha)).astype(f32), "sh": shs.astype(f32),
            "names": names}
