"""glTF 2.0 splats (KHR_gaussian_splatting, clrf/splat/gltf.py): .glb and .gltf written and read
back to float32 rounding at SH degrees 0-3 and awkward counts; the same render; the file
decoded by the ratified specification without clrf's reader (pygltflib's parse, and numpy);
files other tools may write (node transforms, normalized integers, strided views, a .bin
beside the .gltf, several primitives); every malformed file refused with one message naming
it and the attribute."""
import base64
import json
import struct

import numpy as np
import pytest

from clrf.splat import gltf
from clrf.splat.files import read_splat_file, write_splat_file
from clrf.splat.ply import SplatFileError
from test_splat_files import _sigmoid, _splats, _unit_aligned, _within

# the read-back scene renders as the written one to float32 rounding: opacities and scales come
# back within a few float32 ulps (relative 2^-24 each, through exp / log and sigmoid / logit),
# which through the composite of the few hundred Gaussians a pixel meets stays under 1e-5
GLTF_RENDER_TOL = 1e-5
# a node transform is applied in float64 and the result stored as float32: each value within
# one float32 rounding (2^-24 relative) of the exact one, two allowed
F32_ROUND = 2.0 ** -23
F = np.array([1.0, -1.0, -1.0])       # clrf's axes (RDF) -> glTF's (RUB): 180 degrees about x
# the spec's SH constants and polynomials (its "Calculating color" section), x y z a unit
# direction in glTF's axes, in the order of SH_DEGREE_l_COEF_n
SPEC_C1 = 0.4886025119029199
SPEC_C2 = (1.092548430592079, 0.31539156525252, 0.5462742152960395)
SPEC_C3 = (0.5900435899266435, 2.890611442640554, 0.4570457994644657, 0.3731763325901154,
           1.445305721320277)


def spec_colour(coefs, d):
    """The spec's colour (before the +0.5) of SH coefficients [B, 3] towards unit directions
    d [m, 3]: its Color_SH0 + Color_SH1 + Color_SH2 + Color_SH3 written out as it prints them."""
    x, y, z = d.T
    xx, yy, zz = x * x, y * y, z * z
    terms = [np.full_like(x, 0.2820947917738781),
             -SPEC_C1 * y, SPEC_C1 * z, -SPEC_C1 * x,
             SPEC_C2[0] * x * y, -SPEC_C2[0] * y * z, SPEC_C2[1] * (2 * zz - xx - yy),
             -SPEC_C2[0] * x * z, SPEC_C2[2] * (xx - yy),
             -SPEC_C3[0] * y * (3 * xx - yy), SPEC_C3[1] * x * y * z,
             -SPEC_C3[2] * y * (4 * zz - xx - yy), SPEC_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
             -SPEC_C3[2] * x * (4 * zz - xx - yy), SPEC_C3[4] * z * (xx - yy),
             -SPEC_C3[0] * x * (xx - 3 * yy)]
    return np.stack(terms[:len(coefs)], 1) @ coefs


def spec_arrays(g):
    """What the spec says a file of the splats ``g`` (clrf's axes) holds, in glTF's axes
    (float64): POSITION, unit ROTATION x y z w, linear SCALE, OPACITY after the sigmoid."""
    q = np.asarray(g["quats"], np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q = q * np.concatenate([[1.0], F])          # F R F: the vector part turned with the axes
    return {"POSITION": g["means"] * F, "ROTATION": q[:, [1, 2, 3, 0]],
            "SCALE": np.exp(g["log_scales"].astype(np.float64)),
            "OPACITY": _sigmoid(g["opacity_logits"])}


def decode_by_spec(doc, blob):
    """{semantic: float64 [count, width]} of the first primitive of a glTF document (dict) and
    its buffer bytes, by the core specification's accessor rules (float components, tightly
    packed or strided views), and the primitive itself."""
    prim = doc["meshes"][0]["primitives"][0]
    out = {}
    for name, i in prim["attributes"].items():
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        dtype = {5126: "<f4", 5121: "u1"}[acc["componentType"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        a = np.frombuffer(blob, dtype, acc["count"] * width, start).reshape(-1, width)
        out[name] = a.astype(np.float64) / (255.0 if acc.get("normalized") else 1.0)
    return out, prim


def _glb_parts(data):
    """(JSON dict, BIN bytes) of a .glb, by the container's layout (12-byte header, chunks)."""
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    n_json, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON" and n_json % 4 == 0
    doc = json.loads(data[20:20 + n_json])
    n_bin, kind = struct.unpack_from("<I4s", data, 20 + n_json)
    assert kind == b"BIN\0" and n_bin % 4 == 0 and 28 + n_json + n_bin == len(data)
    return doc, data[28 + n_json:]


def check_spec(doc, blob, g):
    """The attributes of a clrf glTF of ``g`` as the spec reads them: the extension's fields,
    POINTS, the accessors' types and POSITION's bounds, and each value."""
    v, prim = decode_by_spec(doc, blob)
    n, B = g["sh"].shape[:2]
    assert EXT in doc["extensionsUsed"] and doc["asset"]["version"] == "2.0"
    assert prim["mode"] == 0
    assert prim["extensions"][EXT]["kernel"] == "ellipse"
    assert prim["extensions"][EXT]["colorSpace"] == "srgb_rec709_display"
    for name, i in prim["attributes"].items():
        acc = doc["accessors"][i]
        assert acc["count"] == n
        if name != "COLOR_0":
            assert acc["componentType"] == 5126, name
    pos = doc["accessors"][prim["attributes"]["POSITION"]]
    assert pos["min"] == v["POSITION"].min(0).tolist()
    assert pos["max"] == v["POSITION"].max(0).tolist()
    want = spec_arrays(g)
    np.testing.assert_array_equal(v["POSITION"], want["POSITION"].astype(np.float32))
    _within(v[ATTR + "ROTATION"], want["ROTATION"], 0, "rotation")
    _within(np.linalg.norm(v[ATTR + "ROTATION"], axis=1), np.ones(n), 0, "|rotation|")
    _within(v[ATTR + "SCALE"] / want["SCALE"], np.ones((n, 3)), 0, "scale / exp(log scale)")
    _within(v[ATTR + "OPACITY"][:, 0], want["OPACITY"], 0, "opacity")
    # the colour the spec computes towards d (glTF's axes) is clrf's towards F d (its own)
    from clrf.references.reference import sh_basis
    d = np.random.default_rng(0).normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    degree = int(round(B ** 0.5)) - 1
    names = [f"{ATTR}SH_DEGREE_{lv}_COEF_{m}" for lv in range(degree + 1)
             for m in range(2 * lv + 1)]
    assert [k for k in prim["attributes"] if "SH_DEGREE" in k] == names
    for i in range(0, n, max(1, n // 7)):
        coefs = np.stack([v[k][i] for k in names])
        np.testing.assert_allclose(spec_colour(coefs, d), sh_basis(d * F, degree) @ g["sh"][i],
                                   rtol=0, atol=1e-12)


EXT, ATTR = gltf.EXTENSION, gltf.ATTR
ACCESSOR_FIELDS = ("bufferView", "byteOffset", "componentType", "count", "type", "normalized",
                   "min", "max")


# ---- round trips ------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gltf_round_trip(tmp_path, suffix, degree):
    """Written and read back: positions and SH exactly, rotations normalised, scales and
    opacities to float32 rounding of exp / log and sigmoid / logit."""
    g = _splats(300, degree, seed=30 + degree)
    path = tmp_path / f"s{suffix}"
    assert write_splat_file(path, **g) == 300
    back = read_splat_file(path)
    np.testing.assert_array_equal(back["means"], g["means"])
    np.testing.assert_array_equal(back["sh"], g["sh"])
    _within(back["quats"], _unit_aligned(g["quats"], back["quats"]), 0, "quats")
    _within(back["log_scales"], g["log_scales"], 0, "log_scales")
    _within(_sigmoid(back["opacity_logits"]), _sigmoid(g["opacity_logits"]), 0, "opacity")
    assert back["names"][:4] == ["POSITION", ATTR + "ROTATION", ATTR + "SCALE", ATTR + "OPACITY"]
    if suffix == ".glb":
        check_spec(*_glb_parts(path.read_bytes()), g)
    else:
        doc = json.loads(path.read_text())
        uri = doc["buffers"][0]["uri"]
        assert uri.startswith("data:application/octet-stream;base64,")
        check_spec(doc, base64.b64decode(uri.split(",", 1)[1]), g)


@pytest.mark.parametrize("n", [0, 1, 255, 256, 257])
def test_gltf_counts(tmp_path, n):
    """No Gaussians: a scene with no mesh (glTF accessors hold at least one element), read as
    none; other counts as they are."""
    g = _splats(n, 1, seed=n)
    path = tmp_path / "c.glb"
    write_splat_file(path, **g)
    back = read_splat_file(path)
    assert back["means"].shape == (n, 3)
    np.testing.assert_array_equal(back["means"], g["means"])
    if n == 0:
        assert "meshes" not in json.loads(gltf.split_glb(path, path.read_bytes())[0])
        assert back["sh"].shape == (0, 1, 3)


def test_gltf_edges(tmp_path):
    """Opacities 0 and 1 and scales of float32's extremes read back finite; a zero quaternion
    is the identity with opacity 0; log scales past float32 are refused."""
    g = _splats(4, 0, seed=3)
    g["opacity_logits"][:3] = [-200.0, 200.0, 0.0]
    g["quats"][2] = 0
    g["log_scales"][3] = [-87.0, 88.0, 0.0]
    path = tmp_path / "e.glb"
    write_splat_file(path, **g)
    back = read_splat_file(path)
    for k in ("opacity_logits", "log_scales"):
        assert np.all(np.isfinite(back[k])), k
    assert _sigmoid(back["opacity_logits"][0]) < 1e-30 < 1 - 1e-7 < _sigmoid(
        back["opacity_logits"][1])
    np.testing.assert_array_equal(back["quats"][2], [1, 0, 0, 0])
    assert _sigmoid(back["opacity_logits"][2]) < 1e-30
    _within(back["log_scales"][3], g["log_scales"][3], 0, "extreme log scales")
    g["log_scales"][1, 0] = 90.0
    with pytest.raises(ValueError, match="log_scales: Gaussian 1 .*float32"):
        write_splat_file(tmp_path / "big.glb", **g)
    assert not (tmp_path / "big.glb").exists()


def test_gltf_renders_the_same(tmp_path, device):
    """clrf's render of the file read back is its render of the scene written, to float32."""
    from clrf.references import reference_splat as rs
    from clrf.splat.raster import SplatCamera, SplatRasterizer
    rng = np.random.default_rng(3)
    n = 3000
    g = {"means": rng.uniform(-1, 1, (n, 3)), "log_scales": rng.uniform(-5, -2, (n, 3)),
         "quats": rng.normal(size=(n, 4)), "opacity_logits": rng.normal(0, 4, n),
         "sh": rng.uniform(-1, 1, (n, 16, 3))}
    g = {k: v.astype(np.float32) for k, v in g.items()}
    cam = SplatCamera(rs.look_at((0.3, -0.2, -3.0), (0, 0, 0)).astype(np.float32), 120.0,
                      120.0, 64.0, 64.0, 128, 128, 0.1)
    r = SplatRasterizer(device, 3)
    want = r.render(g, cam)["rgb"]
    assert want.std() > 0.05                      # a scene, not a blank frame
    for suffix in (".glb", ".gltf"):
        path = tmp_path / f"r{suffix}"
        write_splat_file(path, **g)
        back = read_splat_file(path)
        got = r.render({k: back[k] for k in g}, cam)["rgb"]
        assert np.max(np.abs(got - want)) <= GLTF_RENDER_TOL, suffix


def test_pygltflib_reads_the_glb_and_the_spec_decodes_it(tmp_path):
    """A reader clrf did not write (pygltflib) parses the .glb and the .gltf; the attributes are
    decoded from its object model and buffer by the specification, not by clrf's reader."""
    pygltflib = pytest.importorskip("pygltflib", reason="pygltflib is not installed "
                                    "(`pip install pygltflib`, in the test extra)")
    g = _splats(257, 3, seed=8)
    for suffix in (".glb", ".gltf"):
        path = tmp_path / f"p{suffix}"
        write_splat_file(path, **g)
        doc = pygltflib.GLTF2().load(str(path))
        if suffix == ".gltf":
            doc.convert_buffers(pygltflib.BufferFormat.BINARYBLOB)
        blob = doc.binary_blob()
        assert len(blob) >= doc.buffers[0].byteLength
        as_dict = {
            "asset": {"version": doc.asset.version}, "extensionsUsed": doc.extensionsUsed,
            "meshes": [{"primitives": [{
                "attributes": {k: v for k, v in vars(doc.meshes[0].primitives[0].attributes)
                               .items() if v is not None},
                "mode": doc.meshes[0].primitives[0].mode,
                "extensions": doc.meshes[0].primitives[0].extensions}]}],
            "accessors": [{k: getattr(a, k) for k in ACCESSOR_FIELDS} for a in doc.accessors],
            "bufferViews": [{"byteOffset": b.byteOffset or 0} for b in doc.bufferViews]}
        check_spec(as_dict, blob, g)


# ---- files other tools write ------------------------------------------------------------------
def _doc(arrays: dict, node=None, **prim_extra):
    """(glTF dict, buffer) of one splat primitive from {semantic: (array, componentType,
    normalized)}; ``node``: the node's transform fields."""
    views, accs, attrs, blobs, at = [], [], {}, [], 0
    for i, (name, (a, ctype, norm)) in enumerate(arrays.items()):
        raw = np.ascontiguousarray(a).tobytes()
        blobs.append(raw + bytes(-len(raw) % 4))
        views.append({"buffer": 0, "byteOffset": at, "byteLength": len(raw)})
        accs.append({"bufferView": i, "componentType": ctype, "count": len(a),
                     "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[a.shape[1]],
                     **({"normalized": True} if norm else {})})
        attrs[name] = i
        at += len(blobs[-1])
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": [EXT],
           "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, **(node or {})}],
           "meshes": [{"primitives": [{"attributes": attrs, "mode": 0, "extensions": {EXT: {
               "kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}, **prim_extra}]}],
           "buffers": [{"byteLength": at}], "bufferViews": views, "accessors": accs}
    return doc, b"".join(blobs)


def _float_arrays(g):
    """{semantic: (float32 array, FLOAT, False)} of the splats ``g`` (glTF axes as given)."""
    f = np.float32
    out = {"POSITION": (g["POSITION"].astype(f), 5126, False),
           ATTR + "ROTATION": (g["ROTATION"].astype(f), 5126, False),
           ATTR + "SCALE": (g["SCALE"].astype(f), 5126, False),
           ATTR + "OPACITY": (g["OPACITY"].astype(f)[:, None], 5126, False)}
    for k in range(g["SH"].shape[1]):
        lv = int(np.floor(np.sqrt(k)))
        out[f"{ATTR}SH_DEGREE_{lv}_COEF_{k - lv * lv}"] = (g["SH"][:, k].astype(f), 5126, False)
    return out


def _write_glb(path, doc, blob):
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = (struct.pack("<I4s", len(text), b"JSON") + text
            + struct.pack("<I4s", len(blob), b"BIN\0") + blob)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)


def _foreign(n=40, degree=2, seed=0):
    """Splats as another tool would store them, in glTF's axes (float64)."""
    g = spec_arrays(_splats(n, degree, seed=seed))
    g["SH"] = _splats(n, degree, seed=seed)["sh"].astype(np.float64)
    return g


def test_node_transform_is_applied(tmp_path):
    """A node's translation, rotation and scale move the splats as the spec's covariance
    M R S S R^T M^T says, and turn their colours with them (Wigner-D, here checked as the
    colour towards R d after equalling the colour towards d before)."""
    from clrf.references.reference import sh_basis
    g = _foreign(degree=3)
    rot = np.array([0.3, -0.5, 0.2, 0.79])                        # x y z w
    rot /= np.linalg.norm(rot)
    node = {"translation": [1.0, -2.0, 0.5], "rotation": rot.tolist(), "scale": [2.0, 0.5, 1.5]}
    doc, blob = _doc(_float_arrays(g), node)
    _write_glb(tmp_path / "t.glb", doc, blob)
    back = read_splat_file(tmp_path / "t.glb")
    R = gltf.quat_matrix(rot[[3, 0, 1, 2]][None])[0]
    M = R * np.array(node["scale"])
    want_pos = g["POSITION"].astype(np.float32) @ M.T + node["translation"]
    np.testing.assert_allclose(back["means"] * F, want_pos, rtol=F32_ROUND, atol=0)

    def cov(q_wxyz, s):
        r = gltf.quat_matrix(q_wxyz) * s[:, None, :]
        return r @ np.transpose(r, (0, 2, 1))
    q = g["ROTATION"].astype(np.float32).astype(np.float64)[:, [3, 0, 1, 2]]
    c0 = M @ cov(q, g["SCALE"].astype(np.float32)) @ M.T
    qb = back["quats"].astype(np.float64) * np.concatenate([[1.0], F])     # glTF's axes
    c1 = cov(qb, np.exp(back["log_scales"].astype(np.float64)))
    # s^2 moves by twice the float32 rounding of log s (|log s| 2^-24), the rotation by a few
    # roundings of its components: relative to each Gaussian's largest covariance entry
    bound = F32_ROUND * (2 * np.abs(back["log_scales"]).max(1) + 4)
    err = np.abs(c1 - c0).max((1, 2)) / np.abs(c0).max((1, 2))
    assert np.all(err <= bound), float((err / bound).max())
    d = np.random.default_rng(1).normal(size=(30, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for i in range(0, 40, 9):
        before = spec_colour(g["SH"][i].astype(np.float32), d)
        after = sh_basis((d @ R.T) * F, 3) @ back["sh"][i]           # towards R d, clrf's axes
        # each turned coefficient within a float32 rounding of itself, weighted by the basis
        bound = F32_ROUND * np.abs(sh_basis((d @ R.T) * F, 3)) @ np.abs(back["sh"][i])
        assert np.all(np.abs(after - before) <= bound)


def test_quantised_strided_and_beside(tmp_path):
    """The component types the extension allows (normalized short rotations, byte opacities,
    unsigned short scales), an interleaved (strided) view, a buffer in a .bin beside the
    .gltf, and two primitives of different SH degrees (padded with zeros)."""
    g = _foreign(n=30, degree=1, seed=4)
    arrays = _float_arrays(g)
    rot16 = np.round(g["ROTATION"] * 32767).astype("<i2")
    opa8 = np.round(g["OPACITY"] * 255).astype("u1")[:, None]
    scale16 = np.clip(np.round(g["SCALE"]), 0, 65535).astype("<u2") + 1
    arrays[ATTR + "ROTATION"] = (rot16, 5122, True)
    arrays[ATTR + "OPACITY"] = (opa8, 5121, True)
    arrays[ATTR + "SCALE"] = (scale16, 5123, False)
    doc, blob = _doc(arrays)
    # interleave POSITION with SH degree 0 in one strided view of 24-byte rows
    pos, dc = arrays["POSITION"][0], arrays[ATTR + "SH_DEGREE_0_COEF_0"][0]
    rows = np.concatenate([pos, dc], 1).astype("<f4").tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(rows),
                               "byteStride": 24})
    _acc(doc, "POSITION").update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=0)
    _acc(doc, ATTR + "SH_DEGREE_0_COEF_0").update(bufferView=len(doc["bufferViews"]) - 1,
                                                  byteOffset=12)
    blob += rows
    # a second primitive, SH degree 0, sharing the same accessors
    prim2 = json.loads(json.dumps(doc["meshes"][0]["primitives"][0]))
    prim2["attributes"] = {k: v for k, v in prim2["attributes"].items()
                           if "SH_DEGREE_1" not in k}
    doc["meshes"][0]["primitives"].append(prim2)
    doc["buffers"] = [{"byteLength": len(blob), "uri": "scene%20data.bin"}]
    (tmp_path / "scene data.bin").write_bytes(blob)
    (tmp_path / "q.gltf").write_text(json.dumps(doc))
    back = read_splat_file(tmp_path / "q.gltf")
    assert back["means"].shape == (60, 3) and back["sh"].shape == (60, 4, 3)
    np.testing.assert_array_equal(back["means"][:30], pos * F)
    np.testing.assert_array_equal(back["means"][30:], pos * F)
    np.testing.assert_array_equal(back["sh"][30:, 1:], 0)
    np.testing.assert_array_equal(back["sh"][:30, 0], dc)
    want_q = np.maximum(rot16 / 32767.0, -1.0)[:, [3, 0, 1, 2]] * np.concatenate([[1.0], F])
    _within(back["quats"][:30], want_q, 0, "normalized short rotations")
    _within(_sigmoid(back["opacity_logits"][:30]), np.clip(opa8[:, 0] / 255.0, *gltf.OPACITY_EDGE),
            0, "normalized byte opacities")
    _within(back["log_scales"][:30], np.log(scale16.astype(np.float64)), 0, "ushort scales")


# ---- bad files --------------------------------------------------------------------------------
def _good():
    """A valid clrf .glb of 6 Gaussians, SH degree 1, as (JSON dict, buffer)."""
    from clrf.splat.ply import splat_arrays
    a = splat_arrays(**_splats(6, 1, seed=11))
    return gltf.document(gltf.attributes(a), 6)


def _edit(fn):
    doc, blob = _good()
    fn(doc)
    return gltf.glb_bytes(doc, blob)


def _acc(doc, semantic):
    return doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][semantic]]


def _prim(doc):
    return doc["meshes"][0]["primitives"][0]


def _nan_opacity():
    doc, blob = _good()
    view = doc["bufferViews"][_acc(doc, ATTR + "OPACITY")["bufferView"]]
    b = bytearray(blob)
    b[view["byteOffset"] + 8:view["byteOffset"] + 12] = np.float32(np.nan).tobytes()
    return gltf.glb_bytes(doc, bytes(b))


def _value(semantic, index, value):
    doc, blob = _good()
    view = doc["bufferViews"][_acc(doc, semantic)["bufferView"]]
    b = bytearray(blob)
    at = view["byteOffset"] + 4 * index
    b[at:at + 4] = np.float32(value).tobytes()
    return gltf.glb_bytes(doc, bytes(b))


GOOD = gltf.glb_bytes(*_good())
BAD_GLTF = {
    "cut short (the header)": (GOOD[:10], "cut short: 10 bytes"),
    "cut short (the BIN chunk)": (GOOD[:-40], "cut short: the GLB header says"),
    "cut short (a chunk past the end)": (struct.pack("<4sII", b"glTF", 2, 60) + GOOD[12:60],
                                         "cut short: the JSON chunk of [0-9]+ bytes at byte 20"),
    "wrong magic": (b"GLTF" + GOOD[4:], "not a GLB file: it starts 474c5446"),
    "GLB version 1": (GOOD[:4] + struct.pack("<I", 1) + GOOD[8:], "GLB version 1"),
    "bad JSON": (struct.pack("<4sIII4s", b"glTF", 2, 32, 12, b"JSON") + b"{not json}  ",
                 "not glTF JSON: Expecting property name"),
    "glTF 1.0": (_edit(lambda d: d["asset"].update(version="1.0")), "asset.version '1.0'"),
    "missing ROTATION": (_edit(lambda d: _prim(d)["attributes"].pop(ATTR + "ROTATION")),
                         "attribute KHR_gaussian_splatting:ROTATION missing"),
    "missing SH degree 0": (_edit(lambda d: _prim(d)["attributes"].pop(
        ATTR + "SH_DEGREE_0_COEF_0")), "attribute KHR_gaussian_splatting:SH_DEGREE_0_COEF_0 "
                                      "missing"),
    "partial SH degree 1": (_edit(lambda d: _prim(d)["attributes"].pop(
        ATTR + "SH_DEGREE_1_COEF_1")), "SH_DEGREE_1_COEF_1 missing: the SH coefficients go up"),
    "a NaN opacity": (_nan_opacity(), "attribute KHR_gaussian_splatting:OPACITY of Gaussian 2 "
                                      "is \\[nan\\]"),
    "a negative scale": (_value(ATTR + "SCALE", 4, -1.0), "SCALE of Gaussian 1 .*must not be "
                                                          "negative"),
    "an opacity above 1": (_value(ATTR + "OPACITY", 5, 1.5), "OPACITY of Gaussian 5 .*0..1"),
    "wrong count": (_edit(lambda d: _acc(d, ATTR + "SCALE").update(count=5)),
                    "count does not match: attribute KHR_gaussian_splatting:SCALE holds 5"),
    "a count past the buffer": (_edit(lambda d: _acc(d, ATTR + "SCALE").update(count=9)),
                                "cut short: attribute KHR_gaussian_splatting:SCALE"),
    "wrong type": (_edit(lambda d: _acc(d, ATTR + "SCALE").update(type="VEC4")),
                   "SCALE \\(accessors\\[2\\]\\) is VEC4"),
    "unsigned int positions": (_edit(lambda d: _acc(d, "POSITION").update(
        componentType=5125)), "POSITION .*component type 5125"),
    "sparse": (_edit(lambda d: _acc(d, ATTR + "SCALE").update(sparse={"count": 1})),
               "is sparse"),
    "another kernel": (_edit(lambda d: _prim(d)["extensions"][EXT].update(kernel="disc")),
                       "kernel is 'disc'"),
    "a linear colour space": (_edit(lambda d: _prim(d)["extensions"][EXT].update(
        colorSpace="lin_rec709_display")), "colorSpace is 'lin_rec709_display'"),
    "no colour space": (_edit(lambda d: _prim(d)["extensions"][EXT].pop("colorSpace")),
                        "colorSpace missing"),
    "triangles": (_edit(lambda d: _prim(d).pop("mode")), "mode 4: a splat primitive is POINTS"),
    "meshopt required": (_edit(lambda d: d.update(extensionsRequired=[
        "EXT_meshopt_compression"])), "extensionsRequired names EXT_meshopt_compression"),
    "a mesh, not splats": (_edit(lambda d: _prim(d).pop("extensions")),
                           "no mesh primitive has the KHR_gaussian_splatting extension"),
    "a missing accessor": (_edit(lambda d: _prim(d)["attributes"].update(
        {ATTR + "SCALE": 99})), "refers to accessors\\[99\\]"),
    "a mirroring node": (_edit(lambda d: d["nodes"][0].update(scale=[1, 1, -1])),
                         "mirrors, collapses"),
    "a node cycle": (_edit(lambda d: d["nodes"][0].update(children=[0])), "cycle"),
    "a node matrix of 3 numbers": (_edit(lambda d: d["nodes"][0].update(matrix=[1, 0, 0])),
                                   "nodes\\[0\\]: matrix .*is malformed"),
    "an extension that is no object": (_edit(lambda d: _prim(d)["extensions"].update(
        {EXT: "ellipse"})), "extensions.KHR_gaussian_splatting is not an object"),
}


@pytest.mark.parametrize("case", BAD_GLTF)
def test_bad_glb_files(tmp_path, case):
    data, needle = BAD_GLTF[case]
    path = tmp_path / "bad.glb"
    path.write_bytes(data)
    with pytest.raises(SplatFileError, match=needle) as e:
        read_splat_file(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
    assert "clrf export --splats FILE.glb" in str(e.value)


BAD_JSON_GLTF = {
    "not JSON": (b"{\"asset\": ", "not glTF JSON: Expecting value at line 1"),
    "not UTF-8": (b"\xff\xfe{}", "not UTF-8"),
    "no asset": (b"{}", "no 'asset' object"),
    "bad base64": (None, "the data URI is not base64"),
    "a missing .bin": ("missing.bin", "cannot read .*missing.bin"),
    "a short .bin": ("short.bin", "cut short: buffers\\[0\\] holds 10 bytes"),
}


@pytest.mark.parametrize("case", BAD_JSON_GLTF)
def test_bad_gltf_files(tmp_path, case):
    data, needle = BAD_JSON_GLTF[case]
    path = tmp_path / "bad.gltf"
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        doc, blob = _good()
        doc["buffers"][0]["uri"] = ("data:application/octet-stream;base64,@@@" if data is None
                                    else data)
        if data == "short.bin":
            (tmp_path / data).write_bytes(blob[:10])
        path.write_text(json.dumps(doc))
    with pytest.raises(SplatFileError, match=needle) as e:
        read_splat_file(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
