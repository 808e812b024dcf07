"""Splat files people share (clrf/splat/files.py, spz.py, antimatter.py): Niantic's SPZ and
antimatter15's .splat both ways, against float64 expectations of each format's quantisation;
SPZ's axes (RUB) against the PLY's (RDF) on a hand-made asymmetric Gaussian; every malformed
file refused with one message naming it; and through the command line, a trained model
exported in every format (glTF and the compressed PLY have their own test modules too) that
read back alike, a run started from an .spz, and splat.init_ply taking every ending."""
import gzip
import struct

import numpy as np
import pytest

from clrf.splat import antimatter, spz
from clrf.splat.files import SUFFIXES, read_splat_file, write_splat_file
from clrf.splat.ply import SplatFileError, splat_arrays

# ---- each format's quantisation, as bounds (the arrays come back float32) --------------------
F32_SLACK = 1e-6                      # float32 rounding of values of order 1 (eps 1.2e-7, x8)
# SPZ (spz.py's docstring): each value rounded to its nearest grid point, so within half a step
SPZ_POS_TOL = 0.5 * 2.0 ** -spz.FRACTIONAL_BITS     # 24-bit fixed point, 12 fractional bits
SPZ_ALPHA_TOL = 0.5 / 255                           # uint8 of sigmoid(opacity); also the edges
SPZ_DC_TOL = 0.5 / (255 * spz.COLOR_SCALE)          # uint8 of 255 (0.15 dc + 0.5)
SPZ_DC_RANGE = (-0.5 / spz.COLOR_SCALE, 0.5 / spz.COLOR_SCALE)
SPZ_LOG_SCALE_TOL = 0.5 / 16                        # uint8 of 16 (log scale + 10)
SPZ_LOG_SCALE_RANGE = (-10.0, 255 / 16 - 10.0)
SPZ_SH1_BUCKET, SPZ_SH_REST_BUCKET = 1 << (8 - 6), 1 << (8 - 5)    # 6 and 5 bits of 8
# rotations: each of three components within half a step e, so those three within sqrt(3) e;
# the fourth, recovered from the unit norm and at least 1/2 (the largest of four, version 3;
# w >= 1/2 in the version 2 tests), moves at most sqrt(3) times that: 2 sqrt(3) e in all,
# 5 % over for the second-order terms
SPZ_QUAT_V3_TOL = 1.05 * 2 * np.sqrt(3) * 0.5 * np.sqrt(0.5) / 511   # 9 bits of |q|/sqrt(1/2)
SPZ_QUAT_V2_TOL = 1.05 * 2 * np.sqrt(3) * 0.5 / 127.5                # uint8 of 127.5 (q + 1)
# .splat (antimatter.py's docstring): float32 positions and scales, uint8 colour and rotation
SPLAT_LOG_SCALE_TOL = 8 * np.finfo(np.float32).eps  # float32 exp, then log: a few ulps
SPLAT_DC_TOL = 0.5 / (255 * antimatter.SH_C0)       # uint8 of 255 (0.5 + SH_C0 dc)
SPLAT_DC_RANGE = (-0.5 / antimatter.SH_C0, 0.5 / antimatter.SH_C0)
SPLAT_ALPHA_TOL = 0.5 / 255
SPLAT_QUAT_TOL = 1.0 / 128                          # half a step of 1/128, but +1 -> 255: one


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def _within(got, want, tol, what):
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    err = np.abs(got - want) - (tol + F32_SLACK * (1 + np.abs(want)))
    assert got.shape == want.shape, (what, got.shape, want.shape)
    assert np.all(err <= 0), f"{what}: off by {float(np.max(err)):.3g} past {tol:.3g}"


def _unit_aligned(q, ref):
    """q [n, 4] normalised, each row's sign turned to agree with ref's (q and -q: one turn)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(np.sum(q * np.asarray(ref, np.float64), 1) < 0, -1, 1)[:, None]


def _splats(n, degree, seed=0, dc=(-3.0, 3.0), w_min=None):
    """n Gaussians (float32) with values inside SPZ's ranges; ``w_min``: rotations with
    |w| >= w_min (random sign)."""
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    if w_min is not None:
        angle = rng.uniform(0, 2 * np.arccos(w_min), n)
        axis = rng.normal(size=(n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        quats = np.concatenate([np.cos(angle / 2)[:, None], np.sin(angle / 2)[:, None] * axis], 1)
        quats *= rng.choice([-1.0, 1.0], (n, 1)) * rng.uniform(0.5, 2.0, (n, 1))
    sh = rng.uniform(-1.02, 1.02, (n, (degree + 1) ** 2, 3))      # a little past both ends
    sh[:, 0] = rng.uniform(*dc, (n, 3))
    g = {"means": rng.normal(0, 3, (n, 3)), "log_scales": rng.uniform(-9.5, 5.5, (n, 3)),
         "quats": quats, "opacity_logits": rng.normal(0, 3, n), "sh": sh}
    return {k: v.astype(np.float32) for k, v in g.items()}


def check_spz(back, g, version=3):
    """``back`` (read_spz) against the splats ``g`` it was written from, within SPZ's steps."""
    n, B = g["sh"].shape[:2]
    assert back["sh"].shape == (n, B, 3)
    _within(back["means"], g["means"], SPZ_POS_TOL, "means")
    _within(_sigmoid(back["opacity_logits"]), _sigmoid(g["opacity_logits"]), SPZ_ALPHA_TOL,
            "opacity")
    _within(back["sh"][:, 0], np.clip(g["sh"][:, 0], *SPZ_DC_RANGE), SPZ_DC_TOL, "dc")
    _within(back["log_scales"], np.clip(g["log_scales"], *SPZ_LOG_SCALE_RANGE),
            SPZ_LOG_SCALE_TOL, "log_scales")
    q = _unit_aligned(g["quats"], back["quats"])
    _within(np.linalg.norm(back["quats"], axis=1), np.ones(n), 1e-6, "|quats|")
    tol = SPZ_QUAT_V3_TOL if version >= 3 else SPZ_QUAT_V2_TOL
    err = np.linalg.norm(back["quats"] - q, axis=1)
    assert np.all(err <= tol), (float(err.max()), tol)
    # the SH bytes hold -1 .. 127/128 in SPZ's axes (the grid's 1.0, byte 256, is stored as
    # 255: within half a step still), where a coefficient may have the other sign
    # (spz.sh_signs, checked against the basis below)
    signs = np.concatenate([[1.0], spz.sh_signs(spz.FLIP, B - 1)])[None, :, None]
    for lo, hi, bucket in ((1, 4, SPZ_SH1_BUCKET), (4, 16, SPZ_SH_REST_BUCKET)):
        if B > lo:
            s = signs[:, lo:hi]
            want = np.clip(g["sh"][:, lo:hi] * s, -1.0, 127 / 128) * s
            _within(back["sh"][:, lo:hi], want, bucket / 256, f"sh {lo}..{min(hi, B) - 1}")


def check_splat(back, g):
    """``back`` (read_antimatter) against the splats ``g`` it was written from: in the file's
    order (size times opacity, largest first), within .splat's steps."""
    order = antimatter.size_order(g["log_scales"], g["opacity_logits"])
    key = np.exp(g["log_scales"].astype(np.float64).sum(1)) * _sigmoid(g["opacity_logits"])
    assert np.all(np.diff(key[order]) <= 0)
    assert back["sh"].shape == (len(order), 1, 3)
    np.testing.assert_array_equal(back["means"], g["means"][order])
    _within(back["log_scales"], g["log_scales"][order], SPLAT_LOG_SCALE_TOL, "log_scales")
    _within(back["sh"][:, 0], np.clip(g["sh"][order, 0], *SPLAT_DC_RANGE), SPLAT_DC_TOL, "dc")
    _within(_sigmoid(back["opacity_logits"]), _sigmoid(g["opacity_logits"][order]),
            SPLAT_ALPHA_TOL, "opacity")
    q = g["quats"][order].astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    _within(back["quats"], q / np.where(norm > 0, norm, 1), SPLAT_QUAT_TOL, "quats")


# ---- SPZ --------------------------------------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spz_round_trip(tmp_path, degree):
    g = _splats(300, degree, seed=degree)
    path = tmp_path / "s.spz"
    assert write_splat_file(path, **g) == 300
    back = read_splat_file(path)
    check_spz(back, g)
    assert back["version"] == 3 and back["antialiased"] is False
    # the header as the format describes it, and positions on the 1/4096 grid
    payload = gzip.decompress(path.read_bytes())
    assert struct.unpack_from("<IIIBBBB", payload) == (0x5053474E, 3, 300, degree, 12, 0, 0)
    assert payload[:4] == b"NGSP"
    assert len(payload) == 16 + 300 * (9 + 1 + 3 + 3 + 4 + 3 * ((degree + 1) ** 2 - 1))
    grid = back["means"].astype(np.float64) * 4096
    np.testing.assert_array_equal(grid, np.round(grid))


@pytest.mark.parametrize("degree", [0, 3])
def test_spz_version_2_round_trip(tmp_path, degree):
    """Version 2 (rotations as x, y, z with w >= 0 recovered): read, and written on request;
    rotations within their bound where |w| >= 1/2 (w's precision falls as it nears 0)."""
    g = _splats(200, degree, seed=10 + degree, w_min=0.5)
    path = tmp_path / "s2.spz"
    spz.write_spz(path, **g, version=2)
    payload = gzip.decompress(path.read_bytes())
    assert struct.unpack_from("<II", payload) == (0x5053474E, 2)
    assert len(payload) == 16 + 200 * (9 + 1 + 3 + 3 + 3 + 3 * ((degree + 1) ** 2 - 1))
    back = read_splat_file(path)
    assert back["version"] == 2
    check_spz(back, g, version=2)


def test_spz_big_positions_take_fewer_fractional_bits(tmp_path):
    g = _splats(20, 0, seed=3)
    g["means"][0] = [3000.0, -5000.5, 1.0]       # beyond 2^23 / 2^12 = 2048
    path = tmp_path / "far.spz"
    write_splat_file(path, **g)
    bits = gzip.decompress(path.read_bytes())[13]
    assert bits == 10                             # 5000.5 * 2^10 < 2^23 <= 5000.5 * 2^11
    _within(read_splat_file(path)["means"], g["means"], 0.5 * 2.0 ** -bits, "means")
    g["means"][0, 0] = 1e7                        # past 24 bits with none fractional
    with pytest.raises(ValueError, match="24-bit"):
        write_splat_file(tmp_path / "too_far.spz", **g)


def test_spz_antialiased_flag_and_edges(tmp_path):
    """The anti-aliasing flag both ways; opacities 0 and 1 and a zero quaternion read back
    finite (the quaternion as the identity, fully transparent: clrf culls it either way)."""
    g = _splats(3, 1, seed=5)
    g["opacity_logits"][:2] = [-200.0, 200.0]
    g["quats"][2] = 0
    path = tmp_path / "aa.spz"
    write_splat_file(path, **g, antialiased=True)
    assert gzip.decompress(path.read_bytes())[14] == spz.FLAG_ANTIALIASED
    back = read_splat_file(path)
    assert back["antialiased"] is True
    assert np.all(np.isfinite(back["opacity_logits"]))
    _within(_sigmoid(back["opacity_logits"]), [0.5 / 255, 1 - 0.5 / 255, 0.5 / 255], 1e-6,
            "edges")
    np.testing.assert_allclose(back["quats"][2], [1, 0, 0, 0])


def _quat_matrix(q):
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def test_spz_stores_rub_axes_hand_made(tmp_path):
    """One asymmetric Gaussian in clrf's (the PLY's, RDF) axes, its SPZ bytes decoded here by
    hand: SPZ holds the same scene turned 180 degrees about x (RUB): position (x, -y, -z),
    rotation matrix F R F with F = diag(1, -1, -1), scales as they are (the rotation carries
    the turn), and SH coefficients whose colour towards F d is the PLY's towards d."""
    from clrf.references.reference import sh_basis
    rng = np.random.default_rng(7)
    q = np.array([0.8, 0.1, 0.5, -0.3])
    sh = np.zeros((1, 16, 3))
    colour_bytes = [166, 108, 137]
    sh[0, 0] = (np.array(colour_bytes) / 255.0 - 0.5) / 0.15  # on the colour byte grid
    sh[0, 1:4] = rng.integers(-8, 8, (3, 3)) / 16          # on the 5-bit grid: kept exactly
    sh[0, 4:] = rng.integers(-4, 4, (12, 3)) / 8           # on the 4-bit grid
    path = tmp_path / "one.spz"
    write_splat_file(path, [[1.0, 2.0, 3.0]], [[-1.0, -2.0, -3.0]], [q], [0.0], sh)
    p = gzip.decompress(path.read_bytes())[16:]
    assert p[0:9] == bytes([0x00, 0x10, 0x00, 0x00, 0xE0, 0xFF, 0x00, 0xD0, 0xFF])  # 4096,
    assert p[9] == 128                                      # -8192, -12288: (1, -2, -3) 2^12
    assert list(p[10:13]) == colour_bytes                   # the DC as it is
    assert list(p[13:16]) == [144, 128, 112]                # 16 (log scale + 10)
    comp = int.from_bytes(p[16:20], "little")
    assert comp >> 30 == 3                                  # w (x y z w order) is the largest
    stored = []
    for shift in (20, 10, 0):                               # x, y, z
        f = (comp >> shift) & 0x3FF
        stored.append((-1 if f >> 9 else 1) * np.sqrt(0.5) * (f & 0x1FF) / 511)
    x, y, z = stored
    q_rub = np.array([np.sqrt(1 - x * x - y * y - z * z), x, y, z])
    F = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(_quat_matrix(q_rub), F @ _quat_matrix(q) @ F,
                               atol=2 * SPZ_QUAT_V3_TOL)
    rest = (np.frombuffer(p[20:], np.uint8).reshape(15, 3) - 128.0) / 128
    coeffs = np.concatenate([sh[0, :1], rest])               # [16, 3], DC as it is
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(sh_basis(d @ F, 3) @ coeffs, sh_basis(d, 3) @ sh[0], atol=1e-12)
    back = read_splat_file(path)                             # and turned back on reading
    np.testing.assert_array_equal(back["means"], [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(back["sh"], sh.astype(np.float32))


@pytest.mark.parametrize("flip", [(1, -1, -1), (-1, 1, 1), (1, 1, -1), (-1, -1, -1)])
def test_sh_signs_follow_the_basis(flip):
    """spz.sh_signs against clrf's own SH basis: the colour of the coefficients times their
    signs towards F d is the colour of the coefficients towards d, for any axis flips F."""
    from clrf.references.reference import sh_basis
    rng = np.random.default_rng(1)
    d = rng.normal(size=(40, 3))
    c = rng.normal(size=16)
    signs = np.concatenate([[1.0], spz.sh_signs(flip, 15)])
    np.testing.assert_allclose(sh_basis(d * np.asarray(flip, float), 3) @ (c * signs),
                               sh_basis(d, 3) @ c, atol=1e-12)


def _v4_file(payload: bytes, n_streams=None) -> bytes:
    """A version 4 file of a version 3 payload, its streams stored as they are (the tests
    stand in for the zstd decoder)."""
    magic, _, n, degree, bits, flags, _ = struct.unpack_from("<IIIBBBB", payload)
    sizes = [s for s in spz.stream_sizes(n, degree, 3) if s]
    head = struct.pack("<IIIBBBBI12x", magic, 4, n, degree, bits, flags,
                       len(sizes) if n_streams is None else n_streams, 32)
    return head + b"".join(struct.pack("<QQ", s, s) for s in sizes) + payload[16:]


@pytest.mark.parametrize("degree", [0, 2])
def test_spz_version_4_streams(tmp_path, monkeypatch, degree):
    """Version 4: the header, the stream table and the six (or five) streams in order; the
    zstd decoder is stood in for by the identity, its streams being stored raw here."""
    g = _splats(40, degree, seed=4)
    v3 = tmp_path / "v3.spz"
    write_splat_file(v3, **g)
    v4 = tmp_path / "v4.spz"
    v4.write_bytes(_v4_file(gzip.decompress(v3.read_bytes())))
    monkeypatch.setattr(spz, "_zstd_decompress", lambda blob, size: bytes(blob))
    back, want = read_splat_file(v4), read_splat_file(v3)
    assert back["version"] == 4
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(back[k], want[k])
    v4.write_bytes(_v4_file(gzip.decompress(v3.read_bytes()), n_streams=3))
    with pytest.raises(SplatFileError, match="count does not match"):
        read_splat_file(v4)


def test_spz_version_4_without_a_zstd_decoder(tmp_path, monkeypatch):
    def missing(blob, size):
        raise ImportError("no zstd")
    monkeypatch.setattr(spz, "_zstd_decompress", missing)
    v3 = tmp_path / "v3.spz"
    write_splat_file(v3, **_splats(5, 1))
    v4 = tmp_path / "v4.spz"
    v4.write_bytes(_v4_file(gzip.decompress(v3.read_bytes())))
    with pytest.raises(SplatFileError, match=r"v4\.spz: SPZ version 4 .*zstandard"):
        read_splat_file(v4)


# ---- .splat -----------------------------------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 2])
def test_splat_round_trip(tmp_path, degree):
    g = _splats(300, degree, seed=20 + degree, dc=(-1.7, 1.7))
    path = tmp_path / "s.splat"
    assert write_splat_file(path, **g) == 300
    assert path.stat().st_size == 300 * 32
    check_splat(read_splat_file(path), g)
    # the record as antimatter15's viewer reads it (main.js: 3 f32, 3 f32, 4 u8, 4 u8)
    raw = path.read_bytes()[:32]
    first = antimatter.size_order(g["log_scales"], g["opacity_logits"])[0]
    np.testing.assert_array_equal(np.frombuffer(raw, "<f4", 3), g["means"][first])
    np.testing.assert_allclose(np.frombuffer(raw, "<f4", 3, 12),
                               np.exp(g["log_scales"][first].astype(np.float64)), rtol=1e-6)
    rgba = np.frombuffer(raw, np.uint8, 4, 24)
    assert rgba[3] == round(255 * _sigmoid(g["opacity_logits"][first]))
    q = g["quats"][first].astype(np.float64)
    q /= np.linalg.norm(q)
    np.testing.assert_array_equal(np.frombuffer(raw, np.uint8, 4, 28),
                                  np.clip(np.round(128 * q + 128), 0, 255))


def test_splat_edges(tmp_path):
    """Colours beyond 0..1 clipped, opacities 0 and 1 finite, a zero quaternion kept zero."""
    g = _splats(3, 0, seed=2)
    g["sh"][0, 0] = [10.0, -10.0, 0.0]
    g["opacity_logits"][:] = [-300.0, 300.0, 0.0]
    g["quats"][1] = 0
    path = tmp_path / "e.splat"
    write_splat_file(path, **g)
    back = read_splat_file(path)
    check_splat(back, g)
    assert np.all(np.isfinite(back["opacity_logits"]))
    order = antimatter.size_order(g["log_scales"], g["opacity_logits"])
    assert not np.any(back["quats"][np.flatnonzero(order == 1)])


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_no_gaussians(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    assert write_splat_file(path, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 4)),
                            np.zeros(0), np.zeros((0, 4, 3))) == 0
    back = read_splat_file(path)
    assert back["means"].shape == (0, 3)
    # .splat keeps degree 0; glTF writes no mesh (accessors hold at least one element), so no
    # SH attributes to tell the degree by
    assert back["sh"].shape == (0, 1 if suffix in (".splat", ".glb", ".gltf") else 4, 3)


# ---- bad files --------------------------------------------------------------------------------
def _payload(**header):
    """A valid SPZ payload of 4 Gaussians, SH degree 1, with header fields replaced."""
    a = splat_arrays(**_splats(4, 1, seed=9))
    p = bytearray(spz.pack(a))
    fields = dict(zip(("magic", "version", "n", "degree", "bits", "flags", "reserved"),
                      struct.unpack_from("<IIIBBBB", p)), **header)
    struct.pack_into("<IIIBBBB", p, 0, *fields.values())
    return bytes(p)


def _gz(b):
    return gzip.compress(b, mtime=0)


BAD_SPZ = {
    "cut short (the gzip stream)": (_gz(_payload())[:-12], "cut short"),
    "cut short (the attributes)": (_gz(_payload()[:-5]), "cut short"),
    "cut short (the header)": (_gz(_payload()[:10]), "cut short"),
    "a count too large": (_gz(_payload(n=5)), "cut short: the header says 5 Gaussians"),
    "a count too small": (_gz(_payload(n=3)), "count does not match: the header says 3"),
    "bytes left over": (_gz(_payload() + b"\0" * 7), "count does not match"),
    "wrong magic": (_gz(_payload(magic=0x50534758)), "wrong magic 0x50534758"),
    "unknown version": (_gz(_payload(version=7)), "SPZ version 7"),
    "version 1": (_gz(_payload(version=1)), "SPZ version 1"),
    "SH degree 6": (_gz(_payload(degree=6)), "SH degree 6"),
    "fractional bits 30": (_gz(_payload(bits=30)), "30 fractional bits"),
    "not gzip": (b"ply\nformat ascii 1.0\n", "not an SPZ file"),
    "empty": (b"", "not an SPZ file"),
    "a bad checksum": (_gz(_payload())[:-8] + b"\0" * 8, "gzip stream is corrupt"),
    "version 4 cut short": (b"NGSP\x04\0\0\0", "cut short"),
}
BAD_SPLAT = {
    "cut short": (lambda b: b[:-5], "not a whole number of 32-byte Gaussians"),
    "a NaN position": (lambda b: np.float32(np.nan).tobytes() + b[4:], "position of Gaussian 0"),
    "an infinite scale": (lambda b: b[:12] + np.float32(np.inf).tobytes() + b[16:],
                          "scale of Gaussian 0 .*finite"),
    "a zero scale": (lambda b: b[:12] + bytes(4) + b[16:], "scale of Gaussian 0 .*positive"),
}


@pytest.mark.parametrize("case", BAD_SPZ)
def test_bad_spz_files(tmp_path, case):
    data, needle = BAD_SPZ[case]
    path = tmp_path / "bad.spz"
    path.write_bytes(data)
    with pytest.raises(SplatFileError, match=needle) as e:
        read_splat_file(path)
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)


@pytest.mark.parametrize("case", BAD_SPLAT)
def test_bad_splat_files(tmp_path, case):
    edit, needle = BAD_SPLAT[case]
    path = tmp_path / "bad.splat"
    write_splat_file(path, **_splats(3, 0))
    path.write_bytes(edit(path.read_bytes()))
    with pytest.raises(SplatFileError, match=needle) as e:
        read_splat_file(path)
    assert str(e.value).startswith(f"{path}: ")


@pytest.mark.parametrize("name", ["none.spz", "none.splat", "none.ply", "scene.obj"])
def test_missing_file_and_unknown_endings(tmp_path, name):
    with pytest.raises(SplatFileError, match="cannot read|not a splat file name") as e:
        read_splat_file(tmp_path / name)
    assert name in str(e.value)
    if name.endswith(".obj"):
        assert all(s in str(e.value) for s in SUFFIXES)


@pytest.mark.parametrize("suffix", [".spz", ".splat", ".glb", ".gltf", ".compressed.ply"])
def test_writers_refuse_non_finite_values(tmp_path, suffix):
    g = _splats(3, 1)
    g["log_scales"][1, 2] = np.nan
    with pytest.raises(ValueError, match="log_scales: 1 values are not finite"):
        write_splat_file(tmp_path / f"x{suffix}", **g)
    assert not list(tmp_path.iterdir())
    with pytest.raises(ValueError, match=r"\.ply, \.spz, \.glb, \.gltf, \.compressed\.ply or "
                                         r"\.splat"):
        write_splat_file(tmp_path / "x.obj", **_splats(3, 1))


# ---- through the command line -----------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from clrf.cli.main import main as cli
    out = tmp_path_factory.mktemp("splat_files_run")
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(out), "--max-seconds", "4",
                "--set", "splat.init_points=1000", "--set", "train.final_eval=false"]) == 0
    return out


def test_export_each_format_reads_back_like_the_ply(trained, tmp_path, capsys):
    from clrf.cli.main import main as cli
    paths = {s: tmp_path / f"scene{s}" for s in SUFFIXES}
    for path in paths.values():
        assert cli(["export", "--ckpt", str(trained), "--splats", str(path)]) == 0
    out = capsys.readouterr().out
    assert "(SPZ version 3)" in out and "keeps SH degree 0 only" in out
    ply = read_splat_file(paths[".ply"])
    check_spz(read_splat_file(paths[".spz"]), ply)
    check_splat(read_splat_file(paths[".splat"]), ply)
    assert paths[".spz"].stat().st_size < paths[".ply"].stat().st_size / 5
    from test_splat_compressed import check_compressed
    assert "(glTF binary, KHR_gaussian_splatting)" in out
    assert "(SuperSplat compressed PLY)" in out
    for s in (".glb", ".gltf"):     # float32 kept: the same positions and colours
        g = read_splat_file(paths[s])
        np.testing.assert_array_equal(g["means"], ply["means"])
        np.testing.assert_array_equal(g["sh"], ply["sh"])
        _within(_sigmoid(g["opacity_logits"]), _sigmoid(ply["opacity_logits"]), 0, s)
    check_compressed(read_splat_file(paths[".compressed.ply"]), ply)
    assert paths[".compressed.ply"].stat().st_size < paths[".ply"].stat().st_size / 3


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_init_ply_takes_each_format(tmp_path, suffix):
    """splat.init_ply=FILE of every ending: the first Gaussians are what the file reads as."""
    import dataclasses
    from clrf.data import load_dataset
    from clrf.splat import model as sm
    from clrf.splat.config import SplatConfig
    path = tmp_path / f"start{suffix}"
    write_splat_file(path, **_splats(300, 3, seed=2))
    g = read_splat_file(path)
    sc = dataclasses.replace(SplatConfig.from_preset("tiny"), init_ply=str(path))
    host, where = sm.initial_host(sc, load_dataset(None), cap=10 ** 6, seed=0)
    assert where.startswith(f"300 Gaussians of {path}")
    for k in ("means", "log_scales", "quats", "opacity_logits"):
        np.testing.assert_array_equal(host[k], g[k])


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_a_cut_file_stops_the_run(tmp_path, capsys, suffix):
    """splat.init_ply=FILE cut short, in every format: exit 2 before the run starts, one line
    naming the file."""
    from clrf.cli.main import main as cli
    path = tmp_path / f"cut{suffix}"
    write_splat_file(path, **_splats(300, 1, seed=3))
    path.write_bytes(path.read_bytes()[:-21])
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "no"),
                "--max-seconds", "2", "--set", f"splat.init_ply={path}"]) == 2
    err = capsys.readouterr().err
    assert err.count("clrf: error:") == 1 and str(path) in err
    assert not (tmp_path / "no" / "ckpt.npz").exists()


def test_export_names_every_ending(trained, tmp_path, capsys):
    from clrf.cli.main import main as cli
    assert cli(["export", "--ckpt", str(trained), "--splats", str(tmp_path / "s.obj")]) == 2
    err = capsys.readouterr().err
    assert err.count("clrf: error:") == 1
    assert ".ply, .spz, .glb, .gltf, .compressed.ply or .splat" in err


def test_a_run_starts_from_an_spz(trained, tmp_path, capsys):
    """splat.init_ply=FILE.spz: the first Gaussians are the file's; a bad .spz stops the run
    before it starts (exit 2, one line naming the file)."""
    import dataclasses
    from clrf.cli.main import main as cli
    from clrf.data import load_dataset
    from clrf.splat import model as sm
    from clrf.splat.config import SplatConfig
    path = tmp_path / "start.spz"
    assert cli(["--quiet", "export", "--ckpt", str(trained), "--splats", str(path)]) == 0
    g = read_splat_file(path)
    sc = dataclasses.replace(SplatConfig.from_preset("tiny"), init_ply=str(path))
    host, where = sm.initial_host(sc, load_dataset(None), cap=10 ** 6, seed=0)
    assert where.startswith(f"{len(g['means'])} Gaussians of {path}")
    np.testing.assert_array_equal(host["means"], g["means"])
    run = tmp_path / "run"
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(run), "--max-seconds", "2",
                "--set", f"splat.init_ply={path}", "--set", "train.final_eval=false"]) == 0
    assert (run / "ckpt.npz").exists()
    bad = tmp_path / "bad.spz"
    bad.write_bytes(path.read_bytes()[:-20])
    capsys.readouterr()
    assert cli(["--quiet", "train", "--model", "splat", "--out", str(tmp_path / "no"),
                "--max-seconds", "2", "--set", f"splat.init_ply={bad}"]) == 2
    err = capsys.readouterr().err
    assert err.count("clrf: error:") == 1 and str(bad) in err and "cut short" in err
