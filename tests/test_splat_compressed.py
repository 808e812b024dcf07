"""SuperSplat's compressed PLY (clrf/splat/compressed_ply.py): written and read back within the
bounds its bit widths give, at SH degrees 0-3 and counts around the 256-Gaussian chunk; the
bit layout of a hand-made file; the older 12-property chunk; a compressed file under a plain
.ply name; every malformed file refused with one message naming it and the property; and the
compressed PLY and .splat that gsplat's exporter writes of a clrf scene, read by clrf."""
import numpy as np
import pytest

from clrf.splat import compressed_ply as cp
from clrf.splat.files import read_splat_file, write_splat_file
from clrf.splat.ply import SplatFileError
from test_splat_files import (F32_SLACK, SPLAT_ALPHA_TOL, SPLAT_DC_RANGE, SPLAT_QUAT_TOL, _sigmoid,
                              _splats, _unit_aligned, _within)

# ---- the format's quantisation, from its bit widths (compressed_ply.py's docstring) ----------
POS_STEPS = np.array([(1 << 11) - 1, (1 << 10) - 1, (1 << 11) - 1])   # x, y, z: 11, 10, 11 bits
COLOUR_STEPS = 255                                   # 8 bits over the chunk's colour range
ALPHA_TOL = 0.5 / 255                                # 8 bits of sigmoid(opacity); the edges
SH_STEP = 8.0 / 256                                  # trunc(256 (c / 8 + 0.5)): steps of 1/32
# rotations: three components each within half a step e of 10 bits over +-sqrt(1/2); the
# fourth, recovered from the unit norm and at least 1/2, moves at most sqrt(3) times that:
# 2 sqrt(3) e in all, 5 % over for the second-order terms (as test_splat_files' SPZ bound)
ROT_E = 0.5 / ((1 << 10) - 1) / np.sqrt(0.5)
QUAT_TOL = 1.05 * 2 * np.sqrt(3) * ROT_E
# gsplat's .splat truncates where clrf's rounds: a whole step of colour and opacity
GSPLAT_SPLAT_DC_TOL = 1.0 / (255 * cp.SH_C0)
GSPLAT_ALPHA_TOL = 1.0 / 255


def _within_each(got, want, tol, what):
    """_within with a bound per value (``tol`` broadcast against ``want``)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape, (what, got.shape, want.shape)
    over = np.abs(got - want) - (tol + F32_SLACK * (1 + np.abs(want)))
    assert np.all(over <= 0), f"{what}: off by {float(np.max(over)):.3g} past its bound"


def chunk_bounds(values, n_chunks):
    """(lo, hi) [n, k] of each Gaussian's chunk of ``values`` [n, k] in file order, as float32
    (what the file keeps)."""
    c = np.arange(len(values)) // cp.CHUNK
    lo = np.stack([values[c == i].min(0) for i in range(n_chunks)]).astype(np.float32)
    hi = np.stack([values[c == i].max(0) for i in range(n_chunks)]).astype(np.float32)
    return lo[c].astype(np.float64), hi[c].astype(np.float64)


def check_compressed(back, g, order=None):
    """``back`` (read in file order) against the splats ``g`` written, ``order``: which of g
    each row is (default: clrf's Morton order)."""
    order = cp.morton_order(g["means"]) if order is None else order
    g = {k: np.asarray(g[k], np.float64)[order]
         for k in ("means", "log_scales", "quats", "opacity_logits", "sh")}
    n, B = g["sh"].shape[:2]
    n_chunks = -(-n // cp.CHUNK)
    assert back["sh"].shape == (n, B, 3)
    if n == 0:
        return
    lo, hi = chunk_bounds(g["means"], n_chunks)
    _within_each(back["means"], g["means"], 0.5 * (hi - lo) / POS_STEPS, "means")
    ls = np.clip(g["log_scales"], -cp.SCALE_CLAMP, cp.SCALE_CLAMP)
    lo, hi = np.clip(chunk_bounds(g["log_scales"], n_chunks), -cp.SCALE_CLAMP, cp.SCALE_CLAMP)
    _within_each(back["log_scales"], ls, 0.5 * (hi - lo) / POS_STEPS, "log_scales")
    rgb = 0.5 + cp.SH_C0 * g["sh"][:, 0]
    lo, hi = chunk_bounds(rgb, n_chunks)
    _within_each(0.5 + cp.SH_C0 * back["sh"][:, 0], rgb, 0.5 * (hi - lo) / COLOUR_STEPS,
                 "colour")
    _within(_sigmoid(back["opacity_logits"]), _sigmoid(g["opacity_logits"]), ALPHA_TOL,
            "opacity")
    q = _unit_aligned(g["quats"], back["quats"])
    _within(np.linalg.norm(back["quats"], axis=1), np.ones(n), 1e-6, "|quats|")
    err = np.linalg.norm(back["quats"] - q, axis=1)
    assert np.all(err <= QUAT_TOL), (float(err.max()), QUAT_TOL)
    if B > 1:
        # half a step from the middle of each step, a whole one in the end steps (byte 0 reads
        # -4, byte 255 reads 4); beyond -4..4 clipped
        rest = np.clip(g["sh"][:, 1:], -4.0, 4.0)
        end = (rest < -4.0 + SH_STEP) | (rest >= 4.0 - SH_STEP)
        _within_each(back["sh"][:, 1:], rest, np.where(end, SH_STEP, 0.5 * SH_STEP), "sh rest")


# ---- round trips ------------------------------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_degrees(tmp_path, degree):
    g = _splats(1000, degree, seed=40 + degree)
    g["sh"][:5, 1:] = np.linspace(-4.5, 4.5, 5)[:, None, None]    # both ends and beyond
    g["log_scales"][0] = [-25.0, 22.0, 0.0]                       # past the chunk clamp
    path = tmp_path / "s.compressed.ply"
    assert write_splat_file(path, **g) == 1000
    back = read_splat_file(path)
    check_compressed(back, g)
    assert back["names"][:4] == cp.VERTEX_PROPS
    # the header, 18 floats a chunk, 4 uint32 a Gaussian and a byte a SH coefficient
    data = path.read_bytes()
    header = data.index(b"end_header\n") + 11
    assert len(data) == header + 72 * 4 + 1000 * (16 + 3 * ((degree + 1) ** 2 - 1))


@pytest.mark.parametrize("n", [0, 1, 2, 255, 256, 257, 513])
def test_chunk_counts(tmp_path, n):
    """Counts around the chunk: the header's chunk count is ceil(n / 256); one Gaussian (a
    chunk whose every range is 0) reads back exactly where the range is 0."""
    g = _splats(n, 2, seed=n)
    path = tmp_path / "c.compressed.ply"
    write_splat_file(path, **g)
    assert f"element chunk {-(-n // 256)}\n".encode() in path.read_bytes()[:2000]
    back = read_splat_file(path)
    check_compressed(back, g)
    if n == 1:
        np.testing.assert_array_equal(back["means"], g["means"])
        _within(back["sh"][:, 0], g["sh"][:, 0], 0, "dc of a lone Gaussian")


def test_bit_layout_hand_made(tmp_path):
    """Two Gaussians decoded here by hand: the chunk's bounds, position and scale bits (x in
    the top 11), the rotation's largest index and 10-bit fields, the colour bytes (R first,
    opacity last), the SH bytes channel-major."""
    sh = np.zeros((2, 4, 3))
    sh[0, 0] = [0.0, 1.0, -1.0]
    sh[1, 0] = [1.0, 0.0, 1.0]
    sh[0, 1:, 0] = [1.0, -2.0, 0.0]                 # R of basis 1, 2, 3
    g = {"means": [[0.0, 0.0, 0.0], [1.0, 2.0, 4.0]], "log_scales": [[-1, -2, -3], [1, 2, 3]],
         "quats": [[1.0, 0, 0, 0], [0, 0, -2.0, 0]], "opacity_logits": [0.0, 50.0], "sh": sh}
    path = tmp_path / "h.compressed.ply"
    write_splat_file(path, **g)
    data = path.read_bytes()
    body = data[data.index(b"end_header\n") + 11:]
    chunk = np.frombuffer(body, "<f4", 18)
    np.testing.assert_array_equal(chunk[:12], [0, 0, 0, 1, 2, 4, -1, -2, -3, 1, 2, 3])
    rgb = 0.5 + cp.SH_C0 * sh[:, 0]
    np.testing.assert_array_equal(chunk[12:], np.concatenate([rgb.min(0), rgb.max(0)])
                                  .astype(np.float32))
    v = np.frombuffer(body, "<u4", 8, 72).reshape(2, 4)
    assert v[0, 0] == 0 and v[1, 0] == 0xFFFFFFFF         # min and max of each axis
    assert v[0, 2] == 0 and v[1, 2] == 0xFFFFFFFF
    half = 512                                             # round(0.5 * 1023): a zero component
    assert v[0, 1] == (0 << 30) | (half << 20) | (half << 10) | half     # w largest
    assert v[1, 1] == (2 << 30) | (half << 20) | (half << 10) | half     # y largest, made +
    colour = [(v[:, 3] >> s) & 0xFF for s in (24, 16, 8, 0)]
    np.testing.assert_array_equal(colour[0], [0, 255])     # R: 0.5 + C0 (0, 1), its range
    np.testing.assert_array_equal(colour[1], [255, 0])
    np.testing.assert_array_equal(colour[3], [128, 255])   # round(255 sigmoid(0, 50))
    rest = np.frombuffer(body, "u1", 18, 72 + 32).reshape(2, 9)
    # f_rest_0..2: basis 1..3 of R; trunc(256 (c / 8 + 0.5))
    np.testing.assert_array_equal(rest[0, :3], [160, 64, 128])
    np.testing.assert_array_equal(rest[:, 3:], 128)


def test_old_chunk_layout_and_plain_ply_name(tmp_path):
    """The 12-property chunk (no colour bounds: the colour bytes are the colours), and a
    compressed file named .ply (gsplat writes it under any name) read by its header."""
    g = _splats(300, 0, seed=6, dc=SPLAT_DC_RANGE)
    path = tmp_path / "new.ply"
    write_splat_file(tmp_path / "new.compressed.ply", **g)
    data = (tmp_path / "new.compressed.ply").read_bytes()
    path.write_bytes(data)
    check_compressed(read_splat_file(path), g)
    # rewrite as the old layout: drop the six colour bounds, store the colours themselves
    elements, at = cp.parse_header(path, data)
    chunks = np.frombuffer(data, elements[0][2], elements[0][1], at)
    vertex = np.array(np.frombuffer(data, elements[1][2], elements[1][1],
                                    at + chunks.nbytes))
    rgb = np.clip(0.5 + cp.SH_C0 * g["sh"][cp.morton_order(g["means"]), 0].astype(np.float64),
                  0, 1)
    packed = cp.pack_unorm(rgb, 8)
    vertex["packed_color"] = ((packed[:, 0] << 24) | (packed[:, 1] << 16) | (packed[:, 2] << 8)
                              | (vertex["packed_color"] & 0xFF))
    head = data[:at].decode().replace("".join(f"property float {k}\n" for k in cp.COLOR_PROPS),
                                      "")
    old = np.array([tuple(r)[:12] for r in chunks], [(k, "<f4") for k in cp.CHUNK_PROPS])
    path.write_bytes(head.encode() + old.tobytes() + vertex.tobytes())
    back = read_splat_file(path)
    _within(0.5 + cp.SH_C0 * back["sh"][:, 0], rgb, 0.5 / 255, "colour bytes as colours")


# ---- bad files --------------------------------------------------------------------------------
def _good(n=300, degree=1):
    from clrf.splat.ply import splat_arrays
    return cp.pack(splat_arrays(**_splats(n, degree, seed=12)))


def _header_edit(old, new):
    data = _good()
    end = data.index(b"end_header\n")
    assert old in data[:end]
    return data[:end].replace(old, new, 1) + data[end:]


def _nan_chunk():
    data = bytearray(_good())
    at = data.index(b"end_header\n") + 11 + 3 * 4          # chunk 0, max_x
    data[at:at + 4] = np.float32(np.nan).tobytes()
    return bytes(data)


BAD = {
    "cut short": (_good()[:-7], "cut short: element sh"),
    "cut short in the chunks": (_good()[:_good().index(b"end_header\n") + 11 + 100],
                                "cut short: element chunk"),
    "a count too large": (_header_edit(b"element vertex 300", b"element vertex 600"),
                          "the count does not match: 600 vertices need 3 chunks"),
    "a chunk count off": (_header_edit(b"element chunk 2", b"element chunk 3"),
                          "the count does not match: 300 vertices need 2 chunks of 256, the "
                          "header has 3"),
    "sh rows off": (_header_edit(b"element sh 300", b"element sh 299"), "299 sh rows"),
    "a missing property": (_header_edit(b"property uint packed_scale\n", b""),
                           "vertex properties packed_scale missing"),
    "a float packed property": (_header_edit(b"property uint packed_rotation",
                                             b"property float packed_rotation"),
                                "vertex property packed_rotation is float32, expected uint32"),
    "a missing chunk bound": (_header_edit(b"property float max_scale_y\n", b""),
                              "chunk properties max_scale_y missing"),
    "10 sh properties": (_header_edit(b"property uchar f_rest_8\n",
                                      b"property uchar f_rest_8\nproperty uchar f_rest_9\n"),
                         "10 sh properties"),
    "a NaN bound": (_nan_chunk(), "chunk property max_x of chunk 0 is nan"),
    "no chunk element": (_header_edit(b"element chunk", b"element chunks"),
                         "no 'chunk' element"),
    "ascii": (_header_edit(b"binary_little_endian", b"ascii"), "format ascii 1.0"),
    "a list property": (_header_edit(b"property uint packed_color",
                                     b"property list uchar int packed_color"),
                        "property list uchar int packed_color is not a scalar"),
    "not a PLY": (b"\x1f\x8b\x08\x00", "not a PLY file"),
}


@pytest.mark.parametrize("case", BAD)
def test_bad_compressed_files(tmp_path, case):
    data, needle = BAD[case]
    path = tmp_path / "bad.compressed.ply"
    path.write_bytes(data)
    with pytest.raises(SplatFileError, match=needle) as e:
        read_splat_file(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
    assert "clrf export --splats FILE.compressed.ply" in str(e.value)


def test_writer_refuses_non_finite_values(tmp_path):
    g = _splats(3, 1)
    g["sh"][1, 2, 0] = np.inf
    with pytest.raises(ValueError, match="sh: 1 values are not finite"):
        write_splat_file(tmp_path / "x.compressed.ply", **g)
    assert not list(tmp_path.iterdir())


# ---- a writer clrf did not write: gsplat's exporter -------------------------------------------
def _gsplat_export(g, fmt):
    """The bytes gsplat's export_splats writes of the splats ``g`` (on the CPU)."""
    torch = pytest.importorskip("torch", reason="torch is not installed (the eval extra)")
    exporter = pytest.importorskip("gsplat.exporter", reason="gsplat is not installed "
                                   "(`pip install --no-deps gsplat`; its exporter needs torch "
                                   "only, no CUDA)")
    t = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32)) for k, v in g.items()}
    return exporter.export_splats(t["means"], t["log_scales"], t["quats"], t["opacity_logits"],
                                  t["sh"][:, :1], t["sh"][:, 1:], format=fmt)


def _match(back_means, means):
    """[n] index of the written Gaussian each read-back one is (the nearest position; the
    scene's points lie far apart against the quantisation), checked to be a permutation."""
    from scipy.spatial import cKDTree
    dist, idx = cKDTree(np.asarray(means, np.float64)).query(back_means)
    assert len(set(idx.tolist())) == len(idx)
    return idx


@pytest.mark.parametrize("degree", [0, 3])
def test_gsplat_compressed_ply_reads_back(tmp_path, degree):
    """gsplat writes the compressed PLY of a clrf scene (sorted its own way; Gaussians under
    opacity 1/255 dropped, so none here are); clrf reads it within the format's bounds."""
    g = _splats(1000, degree, seed=50 + degree)
    g["opacity_logits"] = np.clip(g["opacity_logits"], -5.0, None)
    g["log_scales"] = np.clip(g["log_scales"], -19.0, 19.0)
    path = tmp_path / "gsplat.compressed.ply"
    path.write_bytes(_gsplat_export(g, "ply_compressed"))
    back = read_splat_file(path)
    assert len(back["means"]) == 1000
    check_compressed(back, g, order=_match(back["means"], g["means"]))


def test_gsplat_splat_reads_back(tmp_path):
    """gsplat's .splat of a clrf scene (its own order; colours, opacities and rotations
    truncated to bytes where clrf's writer rounds): read by clrf within a whole step."""
    g = _splats(500, 0, seed=7, dc=SPLAT_DC_RANGE)
    path = tmp_path / "gsplat.splat"
    path.write_bytes(_gsplat_export(g, "splat"))
    back = read_splat_file(path)
    idx = _match(back["means"], g["means"])
    w = {k: np.asarray(v, np.float64)[idx] for k, v in g.items()}
    np.testing.assert_array_equal(back["means"], g["means"][idx])
    _within(back["log_scales"], w["log_scales"], 8 * np.finfo(np.float32).eps, "log_scales")
    _within(back["sh"][:, 0], w["sh"][:, 0], GSPLAT_SPLAT_DC_TOL, "dc")
    _within(_sigmoid(back["opacity_logits"]), _sigmoid(w["opacity_logits"]),
            max(GSPLAT_ALPHA_TOL, SPLAT_ALPHA_TOL), "opacity")
    q = w["quats"] / np.linalg.norm(w["quats"], axis=1, keepdims=True)
    _within(back["quats"], q, SPLAT_QUAT_TOL, "quats")
