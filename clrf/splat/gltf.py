"""Gaussian splats as glTF 2.0 with the KHR_gaussian_splatting extension (Khronos; read by
PlayCanvas, Babylon.js, three.js and cesium-native): ``.glb`` (binary) and ``.gltf`` (JSON).

One mesh primitive in POINTS mode (0) whose ``extensions.KHR_gaussian_splatting`` is
``{"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
"sortingMethod": "cameraDistance"}``, and one float32 accessor a Gaussian attribute, values
stored after activation:

  POSITION                                      VEC3   the mean (min / max given, as glTF
                                                       requires)
  KHR_gaussian_splatting:ROTATION               VEC4   the unit quaternion, glTF's x, y, z, w
  KHR_gaussian_splatting:SCALE                  VEC3   linear scales, exp(log scale)
  KHR_gaussian_splatting:OPACITY                SCALAR sigmoid(opacity logit), in 0..1
  KHR_gaussian_splatting:SH_DEGREE_l_COEF_n     VEC3   the SH coefficients, R G B: degree 0
                                                       always, each higher degree whole
                                                       (3, 5, 7 coefficients, m = -l..l)
  COLOR_0                                       VEC4   unsigned byte normalized: the fallback
                                                       colour of viewers without the extension
                                                       (0.5 + SH_C0 dc, clipped to 0..1, sRGB
                                                       decoded to linear; alpha the opacity)

The extension's SH basis (real, with the Condon-Shortley phase, coefficients m = -l..l) is the
one 3DGS and clrf use (cl/sh.h): coefficient k of clrf's [n, B, 3] array is SH_DEGREE_l_COEF_n
with k = l^2 + n, signs and all. The colours are the sRGB display values clrf trains on, hence
srgb_rec709_display.

Coordinates: glTF is right-handed with +y up (and looks down -z from a camera: RUB). clrf's
world frame is taken, as for its PLY and SPZ files, as RDF (x right, y down, z forward, as
COLMAP): the writer turns the scene 180 degrees about x (y and z negated, the quaternion and
the SH coefficients with them: spz.convert_axes), the reader turns it back; the node has no
transform. So clrf's .glb of a scene holds what its .spz holds (Niantic's RDF -> RUB turn).
PlayCanvas's splat-transform turns a PLY 180 degrees about z instead; the two agree on up and
differ by a half turn about it.

``.glb``: the 12-byte header (magic "glTF", version 2, length), a JSON chunk (padded with
spaces) and a BIN chunk (padded with zeros). ``.gltf``: the JSON alone, the buffer embedded
as a base64 ``data:application/octet-stream`` URI (a third larger than the .glb), so that the
one file is the whole scene, written atomically; every glTF loader reads data URIs. The reader
also takes a buffer in a file beside the .gltf (a relative ``uri``), as other tools write.

Kept: every float32 value (the axis turn only negates); the rotation normalised. Lost to
float32 rounding: log scales (exp, then log) and opacity logits (sigmoid, then logit: near
opacity 1 the logit keeps fewer bits, the opacity itself keeps float32's). A zero quaternion
(a Gaussian clrf culls) is written as the identity with opacity 0, invisible too. Opacities 0
and 1 read back as float32's nearest values inside (finite logits), a scale of 0 as float32's
smallest normal number.

Reading files other tools wrote: every primitive with the extension in the default scene,
their node transforms applied (positions, covariances through an SVD, SH rotated degree by
degree); the component types the extension allows (normalized integers for rotation, scale
and opacity; KHR_mesh_quantization's integer positions), strided buffer views. Refused with
one message naming the file and what is wrong: another kernel, a linear colour space (clrf
composites sRGB values), sparse accessors, required extensions clrf does not decode
(meshopt, Draco, SPZ compression), a missing attribute, a partial SH degree, attributes of
different counts, non-finite values, negative scales, opacities outside 0..1.

>>> write_gltf("scene.glb", means, log_scales, quats, opacity_logits, sh)   # sh [n, B, 3]
>>> read_gltf("scene.glb")   # read_splat_ply's dict, names: the attribute semantics
"""
from __future__ import annotations

import base64
import binascii
import json
import struct
from pathlib import Path

import numpy as np

from ..runtime.atomicfile import write_bytes
from ..runtime.version import VERSION
from .ply import SplatFileError, file_bytes, splat_arrays
from .spz import convert_axes

EXTENSION = "KHR_gaussian_splatting"
ATTR = EXTENSION + ":"                      # the attribute semantics' prefix
SPLAT_FIELDS = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                "projection": "perspective", "sortingMethod": "cameraDistance"}
POINTS = 0                                  # mesh.primitive.mode
GLB_MAGIC, GLB_VERSION = b"glTF", 2
GLB_HEADER = struct.Struct("<4sII")         # magic, version, total length
CHUNK_HEADER = struct.Struct("<I4s")        # chunk length, type
CHUNK_JSON, CHUNK_BIN = b"JSON", b"BIN\0"
ARRAY_BUFFER = 34962                        # bufferView.target of vertex attributes
DATA_URI = "data:application/octet-stream;base64,"
SH_C0 = 0.28209479177387814                 # the degree-0 SH basis constant
COEFS = (1, 3, 5, 7)                        # coefficients of SH degree 0..3
F32 = np.finfo(np.float32)
LOG_SCALE_RANGE = (float(np.log(F32.tiny)), float(np.log(F32.max)))   # float32 scales
OPACITY_EDGE = (float(F32.tiny), 1.0 - float(F32.epsneg))            # finite logits
FIX = "export it again with `clrf export --splats FILE.glb`, or pass a .ply or .spz"

# glTF componentType -> numpy dtype; the largest value of each integer type (normalized)
COMPONENTS = {5120: np.dtype("i1"), 5121: np.dtype("u1"), 5122: np.dtype("<i2"),
              5123: np.dtype("<u2"), 5125: np.dtype("<u4"), 5126: np.dtype("<f4")}
FLOAT, UBYTE = 5126, 5121
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
# the types and component types the extension allows an attribute (README, "Attributes");
# POSITION: any, with KHR_mesh_quantization's integer positions
ALLOWED = {"POSITION": ("VEC3", (5120, 5121, 5122, 5123, 5126)),
           ATTR + "ROTATION": ("VEC4", (5126, 5120, 5122)),
           ATTR + "SCALE": ("VEC3", (5126, 5121, 5123)),
           ATTR + "OPACITY": ("SCALAR", (5126, 5121, 5123))}
NORMALIZED_ONLY = {ATTR + "ROTATION", ATTR + "OPACITY"}   # their integer types are normalized
REQUIRED = ["POSITION", ATTR + "ROTATION", ATTR + "SCALE", ATTR + "OPACITY",
            ATTR + "SH_DEGREE_0_COEF_0"]
DECODED = ("KHR_mesh_quantization",)        # required extensions the reader handles


def sh_names(degree: int) -> list:
    """The SH attribute semantics of degrees 0..degree, in clrf's coefficient order."""
    return [f"{ATTR}SH_DEGREE_{lv}_COEF_{m}" for lv in range(degree + 1) for m in range(COEFS[lv])]


def _sigmoid(x):
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# ---- writing --------------------------------------------------------------------------------
def attributes(a: dict) -> dict:
    """{semantic: [n, k] array (float32, or uint8 for COLOR_0)} of splat_arrays ``a`` in glTF's
    axes, in the order the file keeps them."""
    n, B = a["sh"].shape[:2]
    lo, hi = LOG_SCALE_RANGE
    bad = np.flatnonzero(np.any((a["log_scales"] < lo) | (a["log_scales"] > hi), 1))
    if bad.size:
        raise ValueError(f"log_scales: Gaussian {int(bad[0])} has {a['log_scales'][bad[0]]}: "
                         f"glTF keeps float32 scales, log scales {lo:.1f}..{hi:.1f}")
    norm = np.linalg.norm(a["quats"], axis=1)
    zero = norm == 0      # culled by clrf: the identity, fully transparent
    q = np.where(zero[:, None], [1.0, 0, 0, 0], a["quats"] / np.where(zero, 1, norm)[:, None])
    means, q, rest = convert_axes(a["means"], q, a["sh"][:, 1:])
    opacity = np.where(zero, 0.0, _sigmoid(a["opacity_logits"]))
    rgb = _srgb_to_linear(np.clip(0.5 + SH_C0 * a["sh"][:, 0], 0.0, 1.0))
    colour = np.round(255.0 * np.concatenate([rgb, opacity[:, None]], 1)).astype(np.uint8)
    f32 = np.float32
    out = {"POSITION": means.astype(f32), ATTR + "ROTATION": q[:, [1, 2, 3, 0]].astype(f32),
           ATTR + "SCALE": np.exp(a["log_scales"]).astype(f32),
           ATTR + "OPACITY": opacity.astype(f32)[:, None], "COLOR_0": colour}
    sh = np.concatenate([a["sh"][:, :1], rest], 1).astype(f32)
    for k, name in enumerate(sh_names(int(round(B ** 0.5)) - 1)):
        out[name] = sh[:, k]
    return out


def document(attrs: dict, n: int) -> tuple[dict, bytes]:
    """(the glTF JSON, the binary buffer) of ``attrs`` (attributes()): one buffer view and one
    accessor an attribute, each view 4-byte aligned. No Gaussians: a scene with no mesh
    (glTF accessors hold at least one element)."""
    doc = {"asset": {"version": "2.0", "generator": f"clrf {VERSION}"},
           "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"name": "splats"}]}
    if n == 0:
        return doc, b""
    blobs, views, accessors, semantics = [], [], [], {}
    at = 0
    for i, (name, v) in enumerate(attrs.items()):
        raw = np.ascontiguousarray(v).tobytes()
        blobs.append(raw + bytes(-len(raw) % 4))
        views.append({"buffer": 0, "byteOffset": at, "byteLength": len(raw),
                      "target": ARRAY_BUFFER})
        acc = {"bufferView": i, "componentType": FLOAT if v.dtype == np.float32 else UBYTE,
               "count": n, "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[v.shape[1]]}
        if v.dtype == np.uint8:
            acc["normalized"] = True
        if name == "POSITION":
            acc["min"] = [float(x) for x in v.min(0)]
            acc["max"] = [float(x) for x in v.max(0)]
        accessors.append(acc)
        semantics[name] = i
        at += len(blobs[-1])
    doc.update({
        "extensionsUsed": [EXTENSION],
        "nodes": [{"name": "splats", "mesh": 0}],
        "meshes": [{"name": "splats", "primitives": [
            {"attributes": semantics, "mode": POINTS,
             "extensions": {EXTENSION: dict(SPLAT_FIELDS)}}]}],
        "buffers": [{"byteLength": at}], "bufferViews": views, "accessors": accessors})
    return doc, b"".join(blobs)


def glb_bytes(doc: dict, buffer: bytes) -> bytes:
    """The .glb of a glTF JSON and its one buffer (a BIN chunk only where it has bytes)."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = CHUNK_HEADER.pack(len(text), CHUNK_JSON) + text
    if buffer:
        chunks += CHUNK_HEADER.pack(len(buffer), CHUNK_BIN) + buffer
    return GLB_HEADER.pack(GLB_MAGIC, GLB_VERSION, GLB_HEADER.size + len(chunks)) + chunks


def write_gltf(path, means, log_scales, quats, opacity_logits, sh, *, binary=None) -> int:
    """Write n splats to ``path`` as glTF with KHR_gaussian_splatting, atomically: a .glb
    (``binary`` None: by the ending) or a .gltf with its buffer as a data URI. means [n, 3],
    log_scales [n, 3], quats [n, 4] (w, x, y, z), opacity_logits [n], sh [n, B, 3] (B = 1, 4,
    9, 16), in clrf's axes. Returns n."""
    a = splat_arrays(means, log_scales, quats, opacity_logits, sh)
    n = len(a["means"])
    doc, buffer = document(attributes(a), n)
    if binary is None:
        binary = Path(path).suffix.lower() == ".glb"
    if binary:
        write_bytes(path, glb_bytes(doc, buffer))
    else:
        if buffer:
            doc["buffers"][0]["uri"] = DATA_URI + base64.b64encode(buffer).decode("ascii")
        write_bytes(path, json.dumps(doc, indent=1).encode("utf-8"))
    return n


# ---- reading: the container -----------------------------------------------------------------
def _fail(path, msg):
    return SplatFileError(f"{path}: {msg}; {FIX}")


def split_glb(path, data: bytes) -> tuple[bytes, bytes | None]:
    """(JSON bytes, BIN chunk or None) of a .glb; SplatFileError where it is cut short or not
    a version 2 GLB."""
    if len(data) < GLB_HEADER.size:
        raise _fail(path, f"cut short: {len(data)} bytes, less than the 12-byte GLB header")
    magic, version, length = GLB_HEADER.unpack_from(data)
    if version != GLB_VERSION:
        raise _fail(path, f"GLB version {version}: clrf reads glTF 2.0 (GLB version 2)")
    if length > len(data):
        raise _fail(path, f"cut short: the GLB header says {length} bytes, the file has "
                          f"{len(data)}")
    chunks, at = [], GLB_HEADER.size
    while at < length:
        if at + CHUNK_HEADER.size > length:
            raise _fail(path, f"cut short: a chunk header at byte {at} runs past the end "
                              f"({length} bytes)")
        size, kind = CHUNK_HEADER.unpack_from(data, at)
        at += CHUNK_HEADER.size
        if at + size > length:
            raise _fail(path, f"cut short: the {kind.decode('ascii', 'replace').strip()} chunk "
                              f"of {size} bytes at byte {at} runs past the end ({length} "
                              f"bytes)")
        chunks.append((kind, data[at:at + size]))
        at += size
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise _fail(path, "the first GLB chunk is not the JSON chunk")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN else None
    return chunks[0][1], binary


def parse_json(path, text: bytes) -> dict:
    """The glTF JSON object; SplatFileError where it is not JSON or not glTF 2.0."""
    try:
        doc = json.loads(text.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise _fail(path, f"not glTF JSON: not UTF-8 text (byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise _fail(path, f"not glTF JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
        raise _fail(path, "not glTF: the JSON has no 'asset' object")
    version = str(doc["asset"].get("version", ""))
    if not version.startswith("2."):
        raise _fail(path, f"asset.version {version!r}: clrf reads glTF 2.0")
    return doc


def load_buffers(path, doc: dict, glb_bin: bytes | None) -> list:
    """The bytes of each of the document's buffers: the GLB's BIN chunk (a buffer without a
    uri), a base64 data URI, or a file beside ``path``."""
    out = []
    for i, b in enumerate(_list(path, doc, "buffers")):
        uri = b.get("uri")
        if uri is None:
            if glb_bin is None:
                raise _fail(path, f"buffers[{i}] has no uri and the file has no GLB BIN chunk")
            raw = glb_bin
        elif uri.startswith("data:"):
            try:
                raw = base64.b64decode(uri.partition(",")[2], validate=True)
            except (binascii.Error, ValueError) as e:
                raise _fail(path, f"buffers[{i}]: the data URI is not base64 ({e})") from None
        else:
            from urllib.parse import unquote
            where = Path(path).parent / unquote(uri)
            try:
                raw = where.read_bytes()
            except OSError as e:
                raise _fail(path, f"buffers[{i}]: cannot read {where} "
                                  f"({e.strerror or e})") from None
        length = int(b.get("byteLength", -1))
        if len(raw) < length:
            raise _fail(path, f"cut short: buffers[{i}] holds {len(raw)} bytes, its byteLength "
                              f"says {length}")
        out.append(raw)
    return out


def _list(path, doc, key) -> list:
    v = doc.get(key, [])
    if not isinstance(v, list):
        raise _fail(path, f"'{key}' is not a list")
    return v


def _item(path, doc, key, i, what):
    items = _list(path, doc, key)
    if not isinstance(i, int) or not 0 <= i < len(items) or not isinstance(items[i], dict):
        raise _fail(path, f"{what} refers to {key}[{i}], which does not exist "
                          f"({len(items)} {key})")
    return items[i]


def read_accessor(path, doc, buffers, index, semantic) -> np.ndarray:
    """Accessor ``index`` (the attribute ``semantic``) decoded to float64 [count, width]:
    normalized integers as glTF's formulas, a strided view walked, an accessor without a
    buffer view as zeros. Its type and component type are checked against ALLOWED."""
    acc = _item(path, doc, "accessors", index, f"attribute {semantic}")
    kind, ctype, count = acc.get("type"), acc.get("componentType"), acc.get("count")
    want_type, want_ctypes = ALLOWED.get(semantic, ("VEC3", (FLOAT,)))
    if kind != want_type or ctype not in want_ctypes:
        raise _fail(path, f"attribute {semantic} (accessors[{index}]) is {kind} of component "
                          f"type {ctype}: the extension allows {want_type} of "
                          f"{', '.join(map(str, want_ctypes))}")
    if not isinstance(count, int) or count < 1:
        raise _fail(path, f"attribute {semantic} (accessors[{index}]): count {count!r}")
    if "sparse" in acc:
        raise _fail(path, f"attribute {semantic} (accessors[{index}]) is sparse, which clrf "
                          f"does not read")
    dtype, width = COMPONENTS[ctype], WIDTH[kind]
    if "bufferView" not in acc:
        return np.zeros((count, width))
    view = _item(path, doc, "bufferViews", acc["bufferView"], f"accessors[{index}]")
    buf = buffers[_buffer_index(path, doc, view, acc["bufferView"])]
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    elem = dtype.itemsize * width
    stride = int(view.get("byteStride", elem))
    end_view = int(view.get("byteOffset", 0)) + int(view.get("byteLength", 0))
    need = start + stride * (count - 1) + elem
    if stride < elem or need > end_view or end_view > len(buf):
        raise _fail(path, f"cut short: attribute {semantic} (accessors[{index}], {count} x "
                          f"{elem} bytes, stride {stride}) needs bytes {start}..{need} of a "
                          f"buffer view ending at {end_view} in a buffer of {len(buf)}")
    rows = np.ndarray((count, width), dtype, buffer=buf, offset=start, strides=(stride,
                      dtype.itemsize)).astype(np.float64)
    if dtype.kind in "iu" and (acc.get("normalized") or semantic in NORMALIZED_ONLY):
        top = float(np.iinfo(dtype).max)
        rows = np.maximum(rows / top, -1.0)
    return rows


def _buffer_index(path, doc, view, i) -> int:
    b = view.get("buffer")
    if not isinstance(b, int) or not 0 <= b < len(_list(path, doc, "buffers")):
        raise _fail(path, f"bufferViews[{i}] refers to buffers[{b}], which does not exist")
    return b


# ---- reading: the scene ---------------------------------------------------------------------
def node_matrix(path, node: dict, i: int) -> np.ndarray:
    """Node ``i``'s local 4x4 transform: its column-major ``matrix``, or T R S; SplatFileError
    where a field is not numbers of the right count."""
    try:
        if "matrix" in node:
            return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
        m = np.eye(4)
        x, y, z, w = np.asarray(node.get("rotation", [0.0, 0.0, 0.0, 1.0]), np.float64)
        m[:3, :3] = quat_matrix(np.array([[w, x, y, z]]))[0] * np.asarray(
            node.get("scale", [1.0, 1.0, 1.0]), np.float64).reshape(3)
        m[:3, 3] = np.asarray(node.get("translation", [0.0, 0.0, 0.0]), np.float64).reshape(3)
        return m
    except (TypeError, ValueError):
        raise _fail(path, f"nodes[{i}]: matrix (16 numbers), translation (3), rotation (4) "
                          f"or scale (3) is malformed") from None


def quat_matrix(q) -> np.ndarray:
    """Rotation matrices [n, 3, 3] of unit quaternions [n, 4] (w, x, y, z)."""
    w, x, y, z = np.asarray(q, np.float64).T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                    -1).reshape(-1, 3, 3)


def matrix_quat(r) -> np.ndarray:
    """Unit quaternions [n, 4] (w, x, y, z, w >= 0) of rotation matrices [n, 3, 3]."""
    r = np.asarray(r, np.float64)
    # the largest of 4 w^2, 4 x^2, 4 y^2, 4 z^2 picks a well-conditioned formula
    t = np.stack([1 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2], 1 + r[:, 0, 0] - r[:, 1, 1]
                  - r[:, 2, 2], 1 - r[:, 0, 0] + r[:, 1, 1] - r[:, 2, 2],
                  1 - r[:, 0, 0] - r[:, 1, 1] + r[:, 2, 2]], 1)
    k = np.argmax(t, 1)
    s = 2.0 * np.sqrt(np.maximum(t[np.arange(len(r)), k], 1e-300))
    d = {"wx": r[:, 2, 1] - r[:, 1, 2], "wy": r[:, 0, 2] - r[:, 2, 0],
         "wz": r[:, 1, 0] - r[:, 0, 1], "xy": r[:, 0, 1] + r[:, 1, 0],
         "xz": r[:, 0, 2] + r[:, 2, 0], "yz": r[:, 1, 2] + r[:, 2, 1]}
    q = np.choose(k[:, None], [np.stack([s / 4, d["wx"] / s, d["wy"] / s, d["wz"] / s], 1),
                               np.stack([d["wx"] / s, s / 4, d["xy"] / s, d["xz"] / s], 1),
                               np.stack([d["wy"] / s, d["xy"] / s, s / 4, d["yz"] / s], 1),
                               np.stack([d["wz"] / s, d["xz"] / s, d["yz"] / s, s / 4], 1)])
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def sh_rotation(r, degree: int) -> np.ndarray:
    """[B, B] block-diagonal matrix D with sh_basis(R^T d) = sh_basis(d) D^T for rotation R:
    coefficients c [B] of a colour become D^T c under R (fitted per degree by least squares on
    fixed directions; each degree's basis spans a rotation-invariant space, so it is exact to
    rounding)."""
    from ..references.reference import sh_basis
    d = np.random.default_rng(0).normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    y, y_rot = sh_basis(d, degree), sh_basis(d @ np.asarray(r), degree)     # d @ R = R^T d
    out = np.zeros(((degree + 1) ** 2,) * 2)
    for lv in range(degree + 1):
        s = slice(lv * lv, (lv + 1) ** 2)
        out[s, s] = np.linalg.lstsq(y[:, s], y_rot[:, s], rcond=None)[0].T
    return out


def apply_transform(path, m, g: dict, where: str) -> dict:
    """The splats ``g`` (glTF axes) moved by the node transform ``m`` [4, 4]: positions, the
    covariance R S S R^T -> M R S S R^T M^T (its SVD gives the new rotation and scales), SH
    turned by M's rotation. A transform that mirrors or collapses is refused (the extension
    leaves its rendering undefined)."""
    a = m[:3, :3]
    cols = np.linalg.norm(a, axis=0)
    if not np.all(np.isfinite(m)) or np.any(cols <= 0) or np.linalg.det(a / cols) < 0.5:
        raise _fail(path, f"{where}: the node transform {m[:3].tolist()} mirrors, collapses or "
                          f"is not finite, which the extension leaves undefined")
    rot = a / cols
    u, s, _ = np.linalg.svd(a @ quat_matrix(g["quats"]) * g["scales"][:, None, :])
    u[:, :, 2] *= np.sign(np.linalg.det(u))[:, None]                    # a rotation
    sh = g["sh"]
    if sh.shape[1] > 1:
        sh = np.einsum("kj,njc->nkc", sh_rotation(rot, int(round(sh.shape[1] ** 0.5)) - 1).T,
                       sh)
    return dict(g, means=g["means"] @ a.T + m[:3, 3], quats=matrix_quat(u), scales=s, sh=sh)


def splat_primitives(path, doc) -> list:
    """[(primitive, its mesh's global 4x4 transform, where)] of every primitive with the
    extension in the default scene (or, without scenes, under every root node)."""
    nodes = _list(path, doc, "nodes")
    if "scenes" in doc:
        scene = _item(path, doc, "scenes", doc.get("scene", 0), "scene")
        roots = scene.get("nodes", [])
    else:
        children = {c for n in nodes if isinstance(n, dict) for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in children]
    found, stack = [], [(i, np.eye(4), 0) for i in roots]
    while stack:
        i, parent, depth = stack.pop()
        node = _item(path, doc, "nodes", i, "a scene")
        if depth > len(nodes):
            raise _fail(path, f"nodes[{i}]: the node hierarchy has a cycle")
        m = parent @ node_matrix(path, node, i)
        if "mesh" in node:
            mesh = _item(path, doc, "meshes", node["mesh"], f"nodes[{i}]")
            for j, p in enumerate(mesh.get("primitives", [])):
                if isinstance(p, dict) and EXTENSION in p.get("extensions", {}):
                    where = f"meshes[{node['mesh']}].primitives[{j}]"
                    if not isinstance(p["extensions"][EXTENSION], dict):
                        raise _fail(path, f"{where}: extensions.{EXTENSION} is not an object")
                    found.append((p, m, where))
        stack += [(c, m, depth + 1) for c in node.get("children", [])]
    return found


def read_primitive(path, doc, buffers, prim: dict, where: str) -> dict:
    """The splats of one primitive in glTF's axes (float64): means, quats (w, x, y, z),
    scales (linear), opacity, sh [n, B, 3], names."""
    ext = prim["extensions"][EXTENSION]
    for key in ("kernel", "colorSpace"):
        if key not in ext:
            raise _fail(path, f"{where}: {EXTENSION}.{key} missing (the extension requires it)")
    for key in ("kernel", "colorSpace", "projection"):
        if ext.get(key, SPLAT_FIELDS[key]) != SPLAT_FIELDS[key]:
            raise _fail(path, f"{where}: {EXTENSION}.{key} is {ext[key]!r}: clrf renders the "
                              f"{SPLAT_FIELDS[key]!r} {key} only (sRGB display colours, "
                              f"composited before any transfer function)")
    if prim.get("mode", 4) != POINTS:
        raise _fail(path, f"{where}: mode {prim.get('mode', 4)}: a splat primitive is POINTS "
                          f"(mode 0)")
    attrs = prim.get("attributes", {})
    missing = [k for k in REQUIRED if k not in attrs]
    if missing:
        raise _fail(path, f"{where}: attribute {', '.join(missing)} missing (a splat needs "
                          f"{', '.join(REQUIRED)})")
    degree = max([lv for lv in range(1, 4) if any(k in attrs for k in sh_names(lv)[lv * lv:])],
                 default=0)
    gaps = [k for k in sh_names(degree) if k not in attrs]
    if gaps:
        raise _fail(path, f"{where}: attribute {gaps[0]} missing: the SH coefficients go up to "
                          f"degree {degree}, so every coefficient of degrees 0..{degree} must be "
                          f"there")
    names = ["POSITION", ATTR + "ROTATION", ATTR + "SCALE", ATTR + "OPACITY"] + sh_names(degree)
    v = {k: read_accessor(path, doc, buffers, attrs[k], k) for k in names}
    n = len(v["POSITION"])
    for k in names:
        if len(v[k]) != n:
            raise _fail(path, f"{where}: the count does not match: attribute {k} holds "
                              f"{len(v[k])} values, POSITION {n}")
        bad = np.flatnonzero(~np.all(np.isfinite(v[k]), 1))
        if bad.size:
            raise _fail(path, f"{where}: attribute {k} of Gaussian {int(bad[0])} is "
                              f"{v[k][bad[0]].tolist()} ({bad.size} such Gaussians): every "
                              f"value must be finite")
    for k, ok, rule in ((ATTR + "SCALE", v[ATTR + "SCALE"] >= 0, "must not be negative"),
                        (ATTR + "OPACITY", (v[ATTR + "OPACITY"] >= 0)
                         & (v[ATTR + "OPACITY"] <= 1), "must be in 0..1")):
        bad = np.flatnonzero(~np.all(ok, 1))
        if bad.size:
            raise _fail(path, f"{where}: attribute {k} of Gaussian {int(bad[0])} is "
                              f"{v[k][bad[0]].tolist()} ({bad.size} such Gaussians): it "
                              f"{rule}")
    return {"means": v["POSITION"], "quats": v[ATTR + "ROTATION"][:, [3, 0, 1, 2]],
            "scales": v[ATTR + "SCALE"], "opacity": v[ATTR + "OPACITY"][:, 0],
            "sh": np.stack([v[k] for k in sh_names(degree)], 1), "names": list(attrs)}


def read_gltf(path) -> dict:
    """The splats of glTF file ``path`` (.glb or .gltf, told apart by the GLB magic) in clrf's
    axes: read_splat_ply's dict (means, log_scales, quats (w, x, y, z), opacity_logits,
    sh [n, B, 3], names: the attribute semantics). Several splat primitives are concatenated
    (SH padded with zeros to the highest degree); a file with no mesh holds no Gaussians.
    Anything unreadable raises SplatFileError naming the file and what is wrong."""
    path = Path(path)
    data = file_bytes(path, "a glTF file (.glb or .gltf)")
    if data[:4] == GLB_MAGIC:
        text, glb_bin = split_glb(path, data)
    elif path.suffix.lower() == ".glb":
        raise _fail(path, f"not a GLB file: it starts {data[:4].hex()}, not 'glTF'")
    else:
        text, glb_bin = data, None
    doc = parse_json(path, text)
    required = [e for e in doc.get("extensionsRequired", []) if e not in (EXTENSION,) + DECODED]
    if required:
        raise _fail(path, f"extensionsRequired names {', '.join(required)}, which clrf does not "
                          f"decode: write the file without compression")
    prims = splat_primitives(path, doc)
    if not prims and any(isinstance(m, dict) and m.get("primitives")
                         for m in _list(path, doc, "meshes")):
        raise _fail(path, f"no mesh primitive has the {EXTENSION} extension: a mesh, not "
                          f"Gaussian splats")
    buffers = load_buffers(path, doc, glb_bin) if prims else []
    parts = []
    for prim, m, where in prims:
        g = read_primitive(path, doc, buffers, prim, where)
        if not np.array_equal(m, np.eye(4)):
            g = apply_transform(path, m, g, where)
        parts.append(g)
    B = max([p["sh"].shape[1] for p in parts], default=1)
    sh = np.zeros((sum(len(p["means"]) for p in parts), B, 3))
    at = 0
    for p in parts:
        sh[at:at + len(p["means"]), :p["sh"].shape[1]] = p["sh"]
        at += len(p["means"])

    def cat(k, width):
        return np.concatenate([p[k] for p in parts]) if parts else np.zeros((0,) + width)
    means, quats, rest = convert_axes(cat("means", (3,)), cat("quats", (4,)), sh[:, 1:])
    scales = np.maximum(cat("scales", (3,)), F32.tiny)
    opacity = np.clip(cat("opacity", ()), *OPACITY_EDGE)
    f32 = np.float32
    return {"means": means.astype(f32), "log_scales": np.log(scales).astype(f32),
            "quats": quats.astype(f32),
            "opacity_logits": np.log(opacity / (1.0 - opacity)).astype(f32),
            "sh": np.concatenate([sh[:, :1], rest], 1).astype(f32),
            "names": parts[0]["names"] if parts else []}
