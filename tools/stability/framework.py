"""Result rows, tolerances, the Run a case drives, and the building blocks cases share."""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Callable

import clrf
import numpy as np
from clrf.testing import tolerances as TOL
from clrf.references import reference as ref


UNIT = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
ODD_BBOX = np.array([[-1.0, -2.0, 0.25], [3.0, 2.0, 1.75]])   # anisotropic voxels
COLOUR = np.array([0.2, 0.6, 0.9])        # a colour with distinct channels, inside (0, 1)


# ---- tolerances and result rows ----------------------------------------------------------------
@dataclass(frozen=True)
class Tol:
    atol: float
    rtol: float
    name: str    # the constants in clrf/testing/tolerances.py it comes from


def tol(atol_name: str, rtol_name: str | None = None) -> Tol:
    atol = getattr(TOL, atol_name)
    rtol = getattr(TOL, rtol_name) if rtol_name else 0.0
    return Tol(float(atol), float(rtol), atol_name + (f"/{rtol_name}" if rtol_name else ""))


RENDER = tol("RENDER_ATOL", "RENDER_RTOL")
DEPTH = tol("DEPTH_ATOL", "DEPTH_RTOL")
GRAD = tol("GRAD_ATOL", "GRAD_RTOL")
CLOSED = tol("CLOSED_FORM_ATOL", "STAB_CLOSED_FORM_RTOL")
REL = tol("STAB_ZERO_ATOL", "STAB_SEGMENT_SUM_RTOL")
EXACT = tol("STAB_ZERO_ATOL")
LONG_FWD = tol("STAB_LONG_RAY_ATOL", "RENDER_RTOL")
LONG_GRAD = tol("STAB_LONG_GRAD_ATOL", "GRAD_RTOL")
OPT = tol("STAB_OPT_ATOL", "STAB_OPT_RTOL")
OPT_REL = tol("STAB_ZERO_ATOL", "STAB_OPT_RTOL")
OPT_LONG = tol("STAB_OPT_LONG_NORM")
NERF_ENCODE = tol("ENCODE_ATOL")
FINITE = Tol(math.nan, math.nan, "finite only")
RAISES = Tol(math.nan, math.nan, "raises ValueError")


@dataclass
class Row:
    case: str
    group: str
    quantity: str
    max_abs: float
    max_rel: float
    tol: str
    atol: float
    rtol: float
    usage: float
    nonfinite: int
    n: int
    passed: bool
    note: str = ""
    known_bug: bool = False     # the case documents a known kernel bug (Case.xfail)
    ref_max: float = math.nan   # max |reference| (scale of the quantity)


class Run:
    """What a case function receives: the device, the size mode, a seeded RNG and the rows."""

    def __init__(self, device, quick: bool, case: "Case"):
        self.device = device
        self.quick = quick
        self.case = case
        self.rng = np.random.default_rng(zlib.crc32(case.name.encode()))  # stable per case
        self.rows: list[Row] = []

    def size(self, quick, full):
        return quick if self.quick else full

    def _row(self, quantity, **kw):
        self.rows.append(Row(case=self.case.name, group=self.case.group, quantity=quantity, **kw))

    def compare(self, quantity, got, want, tol: Tol | None = None, scale: float = 1.0, note=""):
        """Compare got with want (elementwise |got - want| <= atol + rtol |want|) after dividing
        both by ``scale`` (for cases whose values are ~scale, e.g. SH coefficients of 1e20)."""
        t = tol or self.case.tol
        g = np.asarray(got, np.float64).ravel() / scale
        w = np.broadcast_to(np.asarray(want, np.float64), np.shape(got)).ravel() / scale
        bad = int(np.count_nonzero(~np.isfinite(g)))
        ok = np.isfinite(g) & np.isfinite(w)
        err = np.abs(g - w)[ok]
        wa = np.abs(w)[ok]
        max_abs = float(err.max(initial=0.0))
        max_rel = max_abs / float(wa.max(initial=0.0)) if wa.size and wa.max() > 0 else (
            0.0 if max_abs == 0 else math.inf)
        bound = t.atol + t.rtol * wa
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(err == 0, 0.0, err / bound)
        usage = float(u.max(initial=0.0))
        miss = int(np.count_nonzero(~np.isfinite(w)))
        passed = bad == 0 and miss == 0 and usage <= 1.0
        self._row(quantity, max_abs=max_abs, max_rel=max_rel, tol=t.name, atol=t.atol,
                  rtol=t.rtol, usage=usage, nonfinite=bad, n=int(g.size), passed=passed, note=note,
                  ref_max=float(wa.max(initial=0.0)))

    def finite(self, quantity, *arrays, note=""):
        bad = sum(int(np.count_nonzero(~np.isfinite(np.asarray(a, np.float64)))) for a in arrays)
        n = sum(int(np.size(a)) for a in arrays)
        self._row(quantity, max_abs=math.nan, max_rel=math.nan, tol=FINITE.name, atol=math.nan,
                  rtol=math.nan, usage=0.0, nonfinite=bad, n=n, passed=bad == 0, note=note)

    def raises(self, quantity, fn, must_mention: str):
        """fn() must raise ValueError whose message names ``must_mention``."""
        try:
            fn()
        except ValueError as e:
            msg = str(e)
            ok = must_mention in msg
            note = msg[:120] if ok else f"ValueError without '{must_mention}': {msg[:100]}"
        except Exception as e:  # noqa: BLE001 - any other outcome is the finding
            ok, note = False, f"{type(e).__name__} instead of ValueError: {str(e)[:100]}"
        else:
            ok, note = False, "accepted (no exception)"
        self._row(quantity, max_abs=0.0, max_rel=0.0, tol=RAISES.name, atol=math.nan,
                  rtol=math.nan, usage=0.0 if ok else math.inf, nonfinite=0, n=1, passed=ok,
                  note=note)


@dataclass(frozen=True)
class Case:
    name: str
    group: str
    fn: Callable[[Run], None]
    tol: Tol = RENDER
    xfail: str | None = None
    full_only: bool = False


def run_case(case: Case, device, quick: bool) -> list[Row]:
    run = Run(device, quick, case)
    try:
        case.fn(run)
    except Exception as e:  # noqa: BLE001 - recorded as a failed row, with the error
        run._row("exception", max_abs=math.nan, max_rel=math.nan, tol="-", atol=math.nan,
                 rtol=math.nan, usage=math.inf, nonfinite=0, n=0, passed=False,
                 note=f"{type(e).__name__}: {str(e)[:200]}")
    for r in run.rows:
        r.known_bug = case.xfail is not None
    if not run.rows:
        run._row("no checks", max_abs=math.nan, max_rel=math.nan, tol="-", atol=math.nan,
                 rtol=math.nan, usage=math.inf, nonfinite=0, n=0, passed=False)
    return run.rows


# ---- building blocks ---------------------------------------------------------------------------
def sh_for_colour(shape, colour, degree=0):
    """SH coefficients [.., 3(d+1)^2] giving the view-independent colour (DC term only)."""
    B = (degree + 1) ** 2
    sh = np.zeros(tuple(shape) + (3 * B,), np.float32)
    for ch in range(3):
        sh[..., ch * B] = (np.asarray(colour)[..., ch] - ref.COLOR_OFFSET) / ref.SH_C0
    return sh


def random_grid(rng, shape, degree=1, dens=1.0, negative_frac=0.0):
    d = rng.uniform(0.0, dens, shape)
    if negative_frac:
        d = np.where(rng.random(shape) < negative_frac, -d, d)
    sh = rng.normal(0.0, 0.3, tuple(shape) + (3 * (degree + 1) ** 2,))
    return d.astype(np.float32), sh.astype(np.float32)


def random_rays(rng, n, bbox=UNIT, dist=2.0):
    """Unit-direction rays from outside the box aimed at uniform points inside it."""
    lo, hi = bbox
    target = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = target - d * dist * np.linalg.norm(hi - lo)
    return o.astype(np.float32), d.astype(np.float32)


def axis_rays(n, axis, sign, bbox=UNIT, rng=None, margin=0.5):
    """Rays parallel to ``axis`` (direction sign), starting outside, at transverse positions
    spread over the box (random when rng is given, else a regular set)."""
    lo, hi = bbox
    t = rng.random((n, 3)) if rng is not None else np.stack(
        [np.linspace(0.1, 0.9, n)] * 3, axis=1)
    o = lo + t * (hi - lo)
    o[:, axis] = lo[axis] - margin if sign > 0 else hi[axis] + margin
    d = np.zeros((n, 3))
    d[:, axis] = sign
    return o.astype(np.float32), d.astype(np.float32)


def path_length(origins, dirs, reso, bbox):
    """Float64 length of each ray inside the box (world units), from the reference set-up."""
    return ref.march_setup(origins, dirs, reso, bbox, 1.0)["len"]


def make_grid(run, density, sh, bbox=UNIT, mask=None):
    return clrf.SparseGrid.from_dense(run.device, density, sh, bbox, mask=mask)


def check_render(run, label, density, sh, bbox, o, d, step=0.5, bg=(1.0, 1.0, 1.0),
                 grads=False, mask=None, scale=1.0, fwd_tol=None, grad_tol=None, grid=None,
                 grad_scale=None):
    """Kernel vs float64 reference: rgb, acc, depth (and gradients); returns kernel outputs."""
    g = grid or make_grid(run, density, sh, bbox, mask)
    out = clrf.render_rays(g, o, d, step, bg)
    want = ref.render_forward(density, sh, bbox, o, d, step, bg)
    run.compare(f"{label} rgb", out["rgb"], want["rgb"], fwd_tol or RENDER, scale=scale)
    run.compare(f"{label} acc", out["acc"], want["acc"], fwd_tol or RENDER)
    run.compare(f"{label} depth", out["depth"], want["depth"], DEPTH)
    if grads:
        gr = run.rng.normal(size=(o.shape[0], 3)).astype(np.float32)
        got = clrf.render_rays_backward(g, o, d, gr, step, bg)
        if mask is None:
            mask = (density != 0) | np.any(sh != 0, axis=-1)
        wg = ref.render_backward(density, sh, bbox, o, d, gr, step, bg, mask=mask)
        gs = max(float(np.abs(wg["density"]).max(initial=0)), 1.0) if scale != 1.0 else 1.0
        gs = grad_scale if grad_scale is not None else gs
        run.compare(f"{label} grad density", got["density"], wg["density"], grad_tol or GRAD,
                    scale=gs)
        run.compare(f"{label} grad sh", got["sh"], wg["sh"], grad_tol or GRAD)
    return out


def homogeneous(shape, sigma, colour=COLOUR, degree=0):
    density = np.full(shape, sigma, np.float32)
    return density, sh_for_colour(shape, np.broadcast_to(colour, tuple(shape) + (3,)), degree)
