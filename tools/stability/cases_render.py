"""Renderer cases: stiff densities, closed forms, geometry and value extremes, scale sweep."""
from __future__ import annotations

import math
import time
import warnings

import numpy as np
import clrf
from clrf.testing import tolerances as TOL
from clrf.references import reference as ref

from .framework import (CLOSED, COLOUR, DEPTH, EXACT, GRAD, LONG_FWD, LONG_GRAD, ODD_BBOX, REL,
                        RENDER, UNIT, axis_rays, check_render, homogeneous, make_grid, path_length,
                        random_grid, random_rays, sh_for_colour, tol)


# ---- stiff densities ---------------------------------------------------------------------------
def stiff_sigma_delta(run, sd):
    """Homogeneous unit box with sigma * delta = sd (delta = step / R world units)."""
    R = run.size(4, 16)
    step = 0.5
    delta = step / R
    sigma = np.float32(sd / delta)
    density, sh = homogeneous((R, R, R), sigma)
    mask = np.ones((R, R, R), bool)        # allocated even when sigma == 0
    g = make_grid(run, density, sh, UNIT, mask)
    o1, d1 = axis_rays(8, 0, +1)
    o2, d2 = random_rays(run.rng, run.size(16, 256))
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    L = path_length(o, d, density.shape, UNIT)
    hit = L > 0
    tauL = float(sigma) * L
    acc_cf = -np.expm1(-tauL)
    out = check_render(run, "vs ref", density, sh, UNIT, o, d, step, grads=True, mask=mask,
                       grid=g)
    run.compare("acc vs 1-exp(-sigma L)", out["acc"][hit], acc_cf[hit],
                REL if tauL.max() < math.log(1 / TOL.T_STOP) else CLOSED)
    rgb_cf = COLOUR * acc_cf[:, None] + (1 - acc_cf[:, None])
    run.compare("rgb vs closed form", out["rgb"][hit], rgb_cf[hit], CLOSED)
    black = clrf.render_rays(g, o, d, step, (0.0, 0.0, 0.0))
    run.compare("rgb(bg=1)-rgb(bg=0) vs 1-acc", out["rgb"] - black["rgb"],
                np.broadcast_to(1 - out["acc"][:, None], out["rgb"].shape), RENDER)


def tau_overflow(run):
    """Density 3e38 (the float32 maximum is 3.4e38) on a 100-unit box: sigma * delta = +inf in
    float32. alpha = -expm1(-inf) = 1: the first sample takes all the weight, log T = -inf gives
    T = 0 (no inf - inf), gradients finite."""
    R = 4
    bbox = UNIT * 100.0
    density, sh = homogeneous((R, R, R), 3e38)
    o, d = axis_rays(6, 0, +1, bbox, margin=5.0)
    out = check_render(run, "3e38 x 12.5", density, sh, bbox, o, d, 0.5, grads=True)
    run.compare("acc == 1", out["acc"], np.ones(len(o)), EXACT)
    run.compare("rgb == colour", out["rgb"], np.broadcast_to(COLOUR, out["rgb"].shape), RENDER)
    run.compare("depth == entry + delta/2", out["depth"], np.full(len(o), 5.0 + 12.5 / 2), DEPTH)


def one_hot_voxel(run):
    """A single voxel of density 1e10 on an empty grid: the first sample in its interpolation
    support takes all the weight (acc = 1) and depth is that sample's distance."""
    R = run.size(8, 32)
    i, j, k = R // 2, R // 2 - 1, R // 2
    density = np.zeros((R, R, R), np.float32)
    density[i, j, k] = 1e10
    sh = np.zeros((R, R, R, 3), np.float32)
    g = make_grid(run, density, sh)
    for step in (0.5, 0.37):
        for sign in (+1, -1):
            o, d = axis_rays(1, 0, sign, margin=0.25)
            o[:, 1], o[:, 2] = (j + 0.5) / R, (k + 0.5) / R
            out = check_render(run, f"step {step} dir {sign:+d}", density, sh, UNIT, o, d, step,
                               grads=True, grid=g)
            c = i + 0.5 if sign > 0 else R - (i + 0.5)      # centre, box units from the entry
            kk = math.floor((c - 1.0) / step - 0.5) + 1     # first midpoint strictly past c - 1
            mid = (kk + 0.5) * step
            depth_cf = 0.25 + mid / R
            run.compare(f"step {step} dir {sign:+d} acc == 1", out["acc"], [1.0], RENDER)
            run.compare(f"step {step} dir {sign:+d} depth at support", out["depth"], [depth_cf],
                        DEPTH)
            run.compare(f"step {step} dir {sign:+d} rgb grey", out["rgb"],
                        np.full((1, 3), ref.COLOR_OFFSET), RENDER)


def nearly_opaque(run):
    """Optical depths 6..14 around ln(1/T_STOP) = 9.2: rays stop early or just not."""
    R = run.size(6, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=2, dens=1.0)
    o, d = random_rays(run.rng, run.size(48, 512))
    L = path_length(o, d, density.shape, UNIT)
    med = float(np.median(L[L > 0]))
    for target in (6.0, 9.0, 9.5, 14.0):
        dens = (density * (2 * target / med)).astype(np.float32)    # mean density ~ 0.5
        check_render(run, f"tau~{target:g}", dens, sh, UNIT, o, d, 0.5, grads=True)


def long_ray(run):
    """>= 4096 samples per ray (small step on a long grid), float32 kernel vs float64."""
    Z = run.size(128, 512)
    step = run.size(0.03, 0.1)
    shape = (3, 3, Z)
    bbox = np.array([[0.0, 0.0, 0.0], [3.0 / Z, 3.0 / Z, 1.0]]) * 4
    density, sh = random_grid(run.rng, shape, degree=1, dens=1.0)
    density *= np.float32(3.0 / (0.5 * 4))      # optical depth ~3 over the length: no early stop
    n = run.size(6, 32)
    o, d = axis_rays(n, 2, +1, bbox, rng=run.rng, margin=0.1)
    o[:, :2] = bbox[1, :2] * (0.3 + 0.4 * run.rng.random((n, 2)))  # away from the sides
    d[:, 0] = 2e-3 * run.rng.uniform(-1, 1, n)     # slightly oblique: stays inside over 4 units
    m = ref.march_setup(o, d, shape, bbox, step)
    assert m["nsteps"].min() >= 4096, m["nsteps"].min()
    check_render(run, f"{int(m['nsteps'].min())}+ samples", density, sh, bbox, o, d, step,
                 grads=True, fwd_tol=LONG_FWD, grad_tol=LONG_GRAD)


# sigma L over the unit box (no early termination). Not a power of two: with sigma = 2 every
# tau = 2 delta is a multiple of the ulp of the running log T, so even a plain float32 sum of
# log T would be exact and the check could not tell Kahan from no Kahan.
VERY_LONG_SIGMA = float(np.float32(1.7))


def _very_long_setup(run, shape):
    step = run.size(1e-5, 2e-6)                 # 8e5 / 4e6 samples across 8 voxels
    density, sh = homogeneous(shape, VERY_LONG_SIGMA)
    o, d = axis_rays(4, 0, +1)
    o[:, 1:] = 0.5                              # mid-plane: L = 1 exactly
    return step, density, sh, make_grid(run, density, sh), o, d


def very_long_transmittance(run):
    """~1e6 samples per ray: the transmittance T_end = rgb(bg=1) - rgb(bg=0) comes from the
    Kahan-summed log T alone and must equal exp(-sigma L) to float32 precision."""
    step, density, sh, g, o, d = _very_long_setup(run, (8, 2, 2))
    n = int(math.ceil(8 / step))
    white = clrf.render_rays(g, o, d, step, (1.0, 1.0, 1.0))
    black = clrf.render_rays(g, o, d, step, (0.0, 0.0, 0.0))
    run.compare(f"{n:.0e} samples T_end vs exp(-sigma L)", white["rgb"] - black["rgb"],
                np.full((len(o), 3), math.exp(-VERY_LONG_SIGMA)),
                tol("STAB_ZERO_ATOL", "STAB_VERY_LONG_RTOL"))


def very_long_ray(run):
    """~1e6 samples per ray through a homogeneous slab: acc, rgb and the gradients of a 1-voxel
    grid (closed forms: rgb = c + (bg - c) e^{-sigma L}; dL/dsigma = g.(c - bg) L e^{-sigma L};
    dL/dsh_{ch,0} = g_ch Y_0 (1 - e^{-sigma L})) to float32 precision. Needs compensated
    accumulation of acc / rgb / depth and of the per-cell gradient registers (design principle 9);
    the backward also reads total = g.rgb from the forward."""
    t = tol("STAB_ZERO_ATOL", "STAB_VERY_LONG_RTOL")
    step, density, sh, g, o, d = _very_long_setup(run, (8, 2, 2))
    n = int(math.ceil(8 / step))
    E = math.exp(-VERY_LONG_SIGMA)
    out = clrf.render_rays(g, o, d, step)
    run.compare(f"{n:.0e} samples acc vs 1-exp(-sigma L)", out["acc"], np.full(len(o), 1 - E), t)
    run.compare(f"{n:.0e} samples rgb vs closed form", out["rgb"],
                np.broadcast_to(COLOUR + (1 - COLOUR) * E, out["rgb"].shape), t)
    step, density, sh, g, o, d = _very_long_setup(run, (1, 1, 1))
    step = step / 8                              # the same number of samples over one voxel
    gr = np.tile(np.array([[0.7, -0.4, 1.1]], np.float32), (len(o), 1))
    grads = clrf.render_rays_backward(g, o, d, gr, step)
    gsum = gr.astype(np.float64).sum(0)
    run.compare("1-voxel grid: grad density vs closed form", grads["density"].ravel(),
                [float(gsum @ (COLOUR - 1.0)) * E], t)
    run.compare("1-voxel grid: grad sh (DC) vs closed form", grads["sh"].ravel()[[0, 1, 2]],
                gsum * ref.SH_C0 * (1 - E), t)


def step_overflow(run):
    """A step so small that a ray needs more than 2^31 - 1 samples (int nsteps) must be
    rejected with a ValueError rather than rendered as an empty ray."""
    R = 8
    density, sh = homogeneous((R, R, R), 2.0)
    g = make_grid(run, density, sh)
    o, d = axis_rays(2, 0, +1)
    out = clrf.render_rays(g, o, d, 1e-6)           # 8e6 samples: fine
    run.finite("step 1e-6 (8e6 samples) outputs", out["rgb"], out["acc"])
    run.raises("step 1e-9 (8e9 samples) rejected", lambda: clrf.render_rays(g, o, d, 1e-9),
               "step")


def world_scale(run):
    """Box scaled by s in [1e-10, 1e10] with density / s: same optical depths, so the same rgb
    and acc (depth scales by s); gradients finite."""
    R = run.size(4, 12)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=4.0)
    o, d = random_rays(run.rng, run.size(24, 256))
    base = clrf.render_rays(make_grid(run, density, sh), o, d)
    for sc in (1e-10, 1e-5, 1e5, 1e10):
        bbox = UNIT * sc + 0.25 * sc
        oo = (o.astype(np.float64) * sc + 0.25 * sc).astype(np.float32)
        dens = (density / np.float64(sc)).astype(np.float32)
        g = make_grid(run, dens, sh, bbox)
        # dL/dsigma is proportional to the segment lengths, i.e. to sc: compare it in the units
        # of the unit-box problem (divided by sc), like rgb and acc.
        out = check_render(run, f"x{sc:g}", dens, sh, bbox, oo, d, grid=g, grads=True,
                           grad_scale=sc)
        run.compare(f"x{sc:g} rgb vs unit box", out["rgb"], base["rgb"], RENDER)
        run.compare(f"x{sc:g} depth/s vs unit box", out["depth"] / sc, base["depth"] + 0.0,
                    DEPTH)


# ---- closed forms ------------------------------------------------------------------------------
def slab(run, sigma):
    """Homogeneous slab on an anisotropic box: acc = 1 - exp(-sigma L) (L = path length)."""
    shape = run.size((6, 5, 4), (24, 20, 16))
    density, sh = homogeneous(shape, sigma)
    g = make_grid(run, density, sh, ODD_BBOX)
    o, d = random_rays(run.rng, run.size(64, 1024), ODD_BBOX)
    L = path_length(o, d, shape, ODD_BBOX)
    hit = L > 0
    out = clrf.render_rays(g, o, d, 0.5, (1.0, 1.0, 1.0))
    black = clrf.render_rays(g, o, d, 0.5, (0.0, 0.0, 0.0))
    acc_cf = -np.expm1(-np.float64(np.float32(sigma)) * L)
    no_stop = sigma * L.max() < math.log(1 / TOL.T_STOP)
    run.compare("acc vs 1-exp(-sigma L)", out["acc"][hit], acc_cf[hit], REL if no_stop else CLOSED,
                note="early termination applies" if not no_stop else "")
    run.compare("rgb vs closed form", out["rgb"][hit],
                COLOUR * acc_cf[hit, None] + (1 - acc_cf[hit, None]), CLOSED)
    run.compare("rgb(bg=1)-rgb(bg=0) vs 1-acc", out["rgb"] - black["rgb"],
                np.broadcast_to(1 - out["acc"][:, None], out["rgb"].shape), RENDER)
    run.compare("miss -> acc 0", out["acc"][~hit], np.zeros(int((~hit).sum())), EXACT)
    run.finite("outputs", out["rgb"], out["acc"], out["depth"])


def ramp(run, axis, sign):
    """Density linear along one axis (centre values a + b (i + 0.5)): trilinear interpolation is
    exact between the outermost centres and constant beyond, so the optical depth along the axis
    is R (d_0 + d_{R-1}) / 2 voxels; midpoint samples are exact when segment ends fall on the
    half-voxel kinks (steps 0.5 and 0.25 from an entry on a face)."""
    R = run.size(8, 32)
    shape = [run.size(3, 8)] * 3
    shape[axis] = R
    i = np.arange(R) + 0.5
    a, b = 0.2, 2.0 / R           # sigma per world unit in the unit box
    prof = a + b * i
    density = np.broadcast_to(prof.reshape([-1 if ax == axis else 1 for ax in range(3)]),
                              shape).astype(np.float32)
    sh = sh_for_colour(shape, np.broadcast_to(COLOUR, tuple(shape) + (3,)))
    tau = R * (float(density.flat[0]) * 0 + (np.float64(np.float32(prof[0]))
                                            + np.float64(np.float32(prof[-1])))) / 2 / R
    o, d = axis_rays(run.size(8, 64), axis, sign, rng=run.rng)
    acc_cf = -np.expm1(-tau)
    g = make_grid(run, density, sh)
    for step in (0.5, 0.25):
        out = check_render(run, f"step {step}", density, sh, UNIT, o, d, step, grid=g)
        run.compare(f"step {step} acc vs exact optical depth", out["acc"],
                    np.full(len(o), acc_cf), REL)
        run.compare(f"step {step} rgb vs closed form", out["rgb"],
                    np.broadcast_to(COLOUR * acc_cf + (1 - acc_cf), out["rgb"].shape), REL)


def segment_sum(run):
    """Tiny homogeneous density: acc = 1 - exp(-sigma L) ~ sigma L to 1e-6 relative, so the
    clipped segments must add up to the path length, for steps that do not divide it."""
    shape = run.size((5, 6, 7), (20, 24, 28))
    sigma = 1e-6
    density, sh = homogeneous(shape, sigma)
    g = make_grid(run, density, sh, ODD_BBOX)
    o, d = random_rays(run.rng, run.size(64, 1024), ODD_BBOX)
    L = path_length(o, d, shape, ODD_BBOX)
    hit = L > 0
    for step in (0.3, 0.7, 1.3, 3.1):
        out = clrf.render_rays(g, o, d, step)
        run.compare(f"step {step} acc/(1-exp(-sigma L))", out["acc"][hit],
                    -np.expm1(-np.float64(np.float32(sigma)) * L[hit]), REL)


def linear_colour_setup(R, sigma=3.0):
    """Homogeneous sigma, colour c(p) = 0.2 + 0.6 clip(p, .5, R-.5)/R along x (box units p)."""
    i = np.arange(R) + 0.5
    c = 0.2 + 0.6 * i / R
    colour = np.zeros((R, 2, 2, 3))
    colour[...] = np.array([1.0, 0.8, 0.6])[None, None, None, :] * c[:, None, None, None]
    density = np.full((R, 2, 2), sigma, np.float32)
    return density, sh_for_colour((R, 2, 2), colour)


def linear_colour_exact(R, sigma, bg=1.0):
    """rgb of a +x ray through linear_colour_setup: integral of sigma e^{-sigma s} c(s) ds on
    the three pieces of c (constant, linear, constant), plus bg e^{-sigma L}; L = 1."""
    def piece(A, B, s0, s1):    # integral of sigma e^{-sigma s} (A + B s) over [s0, s1]
        F = lambda s: -math.exp(-sigma * s) * (A + B * s + B / sigma)  # noqa: E731
        return F(s1) - F(s0)
    sa, sb = 0.5 / R, (R - 0.5) / R
    slope = 0.6                 # c(s) = 0.2 + 0.6 s on [sa, sb] (s = p / R)
    tot = (piece(0.2 + 0.6 * sa, 0.0, 0.0, sa) + piece(0.2, slope, sa, sb)
           + piece(0.2 + 0.6 * sb, 0.0, sb, 1.0))
    return np.array([1.0, 0.8, 0.6]) * tot + bg * math.exp(-sigma)


def convergence_table(device, quick: bool, n_rays=None, repeats=3):
    """(step, samples per ray, max rgb error, seconds) of the renderer on the closed form."""
    R = 16 if quick else 32
    sigma = 3.0
    density, sh = linear_colour_setup(R, sigma)
    g = clrf.SparseGrid.from_dense(device, density, sh, UNIT)
    n = n_rays or (256 if quick else 8192)
    rng = np.random.default_rng(1)
    o, d = axis_rays(n, 0, +1, rng=rng, margin=0.5)
    o[:, 1:] = (0.05 + 0.9 * rng.random((n, 2))).astype(np.float32)
    want = linear_colour_exact(R, sigma)
    steps = [2.0 ** -k for k in range(0, 5 if quick else 9)]
    rows = []
    for step in steps:
        clrf.render_rays(g, o[:1], d[:1], step)
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            out = clrf.render_rays(g, o, d, step)
            ts.append(time.perf_counter() - t)
        err = float(np.abs(out["rgb"] - want).max())
        rows.append(dict(step=step, samples=int(math.ceil(R / step)), max_err=err,
                         seconds=min(ts), rays=n))
    return rows


def convergence(run):
    """Midpoint quadrature of a linear colour ramp converges at order 2 in the step: each
    halving of the step in the asymptotic range (1/2 -> 1/16; the errors, ~1e-4..2e-6, stay well
    above the float32 floor ~1e-7) divides the error by ~4."""
    rows = convergence_table(run.device, True, n_rays=64, repeats=1)[1:5]
    errs = [r["max_err"] for r in rows]
    orders = [math.log2(e0 / e1) for e0, e1 in zip(errs, errs[1:])]
    run.compare("observed order, steps 1/2 -> 1/16", orders, [2.0] * len(orders),
                tol("STAB_ORDER_ATOL"), note="errors " + ", ".join(f"{e:.1e}" for e in errs))


# ---- geometry extremes -------------------------------------------------------------------------
def tiny_dirs(run):
    """Direction components exactly 0, +-1e-30 and subnormal (ray.h slab method: no NaN, the
    same result as 0)."""
    R = run.size(5, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=2, dens=4.0)
    g = make_grid(run, density, sh)
    o, d = axis_rays(run.size(12, 128), 1, +1, rng=run.rng)
    outs = {}
    for tiny in (0.0, 1e-30, -1e-30, 1e-40, -1e-45):     # 1e-40, 1e-45: float32 subnormals
        dd = d.copy()
        dd[:, 0] = tiny
        dd[:, 2] = -tiny
        outs[tiny] = check_render(run, f"components {tiny:g}", density, sh, UNIT, o, dd, 0.5,
                                  grads=True, grid=g)
    for tiny in (1e-30, -1e-30, 1e-40, -1e-45):
        run.compare(f"{tiny:g} vs 0", outs[tiny]["rgb"], outs[0.0]["rgb"], RENDER)


def dir_scale(run):
    """Unnormalised directions: scaled by 2^k exactly (bitwise identical result) and by 10^k
    (float32 rounding of the input only)."""
    R = run.size(5, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=2, dens=4.0)
    g = make_grid(run, density, sh)
    o, d = random_rays(run.rng, run.size(32, 512))
    base = clrf.render_rays(g, o, d)
    for k in (-66, -33, 33, 66):
        out = clrf.render_rays(g, o, (d * np.float32(2.0 ** k)).astype(np.float32))
        for q in ("rgb", "acc", "depth"):
            run.compare(f"x2^{k} {q} identical", out[q], base[q], EXACT)
    for s in (1e-20, 1e-10, 1e10, 1e20):
        ds = (d.astype(np.float64) * s).astype(np.float32)
        out = check_render(run, f"x{s:g}", density, sh, UNIT, o, ds, 0.5, grid=g)
        run.compare(f"x{s:g} rgb vs unscaled", out["rgb"], base["rgb"], RENDER)


def far_origin(run):
    """Origins 1e4 units outside the box: double-precision set-up enters at the right point."""
    R = run.size(5, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=4.0)
    g = make_grid(run, density, sh)
    o, d = random_rays(run.rng, run.size(32, 512), dist=1.0)
    far = (o.astype(np.float64) - 1e4 * d).astype(np.float32)
    out = check_render(run, "1e4 away", density, sh, UNIT, far, d, 0.5, grads=True, grid=g)
    # The same line started 1 unit from the box (origin rounded to float32 at ~1e-7, not at
    # the ~1e-3 of a float32 number near 1e4): same result to rendering tolerance.
    near = (far.astype(np.float64) + 1e4 * d.astype(np.float64)).astype(np.float32)
    run.compare("1e4 away rgb vs same ray from near", out["rgb"],
                clrf.render_rays(g, near, d)["rgb"], RENDER)


def grazing(run):
    """Rays in face planes, along edges, through corners, and at tiny angles to faces."""
    R = run.size(4, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=4.0)
    g = make_grid(run, density, sh)
    o = np.array([[-1, 0, 0.5], [-1, 1, 0.5], [-1, 0.5, 0], [-1, 0.5, 1],   # in face planes
                  [-1, 0, 0], [-1, 1, 1], [0.5, -1, 1], [1, 1, -1],        # along edges
                  [-1, -1, -1], [2, 2, 2], [-1, -1, 2],                     # through corners
                  [-1, 1e-7, 0.5], [-1, 1 - 1e-7, 0.5], [-1, 0.5, -1e-7],   # just in/out
                  [-1, 0.0, 0.3], [0.5, 0.5, -1]], np.float32)
    d = np.array([[1, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0],
                  [1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                  [1, 1, 1], [-1, -1, -1], [1, 1, -1],
                  [1, 0, 0], [1, 0, 0], [1, 0, 0],
                  [1, 1e-6, 0], [1e-7, 0, 1]], np.float32)
    check_render(run, "grazing", density, sh, UNIT, o, d, 0.5, grads=True, grid=g)


def inside_start(run):
    """Origins inside the grid: on voxel faces, edges, corners (integer box coordinates), at
    centres and random points."""
    R = run.size(4, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=4.0)
    g = make_grid(run, density, sh)
    n = run.size(24, 256)
    lattice = run.rng.integers(0, R + 1, (n, 3)) / R
    centre = (run.rng.integers(0, R, (n, 3)) + 0.5) / R
    face = lattice.copy()
    face[:, 0] = centre[:, 0]
    o = np.concatenate([lattice, centre, face, run.rng.random((n, 3))]).astype(np.float32)
    d = run.rng.normal(size=o.shape)
    d[: n // 2, 1:] = 0                               # some axis-aligned along the lattice
    d = d.astype(np.float32)
    check_render(run, "inside", density, sh, UNIT, o, d, 0.5, grads=True, grid=g)


def degenerate(run, shape):
    """1-voxel and flat grids: interpolation clamps, the march still covers the box."""
    density, sh = random_grid(run.rng, shape, degree=1, dens=3.0)
    bbox = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 2.0]])
    o, d = random_rays(run.rng, run.size(32, 256), bbox)
    check_render(run, f"{shape}", density, sh, bbox, o, d, 0.5, grads=True)


def pruned(run):
    """No allocated voxel: rgb = background, acc = depth = 0, gradients 0."""
    R = run.size(4, 16)
    density = np.zeros((R, R, R), np.float32)
    sh = np.zeros((R, R, R, 12), np.float32)
    g = make_grid(run, density, sh)
    o, d = random_rays(run.rng, run.size(32, 256))
    bg = (0.3, 0.5, 0.7)
    out = clrf.render_rays(g, o, d, 0.5, bg)
    run.compare("rgb == background", out["rgb"],
                np.broadcast_to(np.float32(bg), out["rgb"].shape), EXACT)
    run.compare("acc == 0", out["acc"], np.zeros(len(o)), EXACT)
    run.compare("depth == 0", out["depth"], np.zeros(len(o)), EXACT)
    gr = clrf.render_rays_backward(g, o, d, np.ones((len(o), 3), np.float32), 0.5, bg)
    run.compare("grad == 0", np.concatenate([gr["density"].ravel(), gr["sh"].ravel()]),
                0.0, EXACT)


# ---- value extremes ----------------------------------------------------------------------------
def negative_density(run):
    R = run.size(5, 16)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=4.0)
    o, d = random_rays(run.rng, run.size(32, 256))
    mask = np.ones(density.shape, bool)
    neg = -np.abs(density) - 1e9 * (run.rng.random(density.shape) < 0.2)
    out = check_render(run, "all negative", neg.astype(np.float32), sh, UNIT, o, d, grads=True,
                       mask=mask)
    run.compare("all negative acc == 0", out["acc"], np.zeros(len(o)), EXACT)
    mixed = np.where(run.rng.random(density.shape) < 0.4, -density * 1e3, density)
    check_render(run, "mixed signs", mixed.astype(np.float32), sh, UNIT, o, d, grads=True,
                 mask=mask)


def huge_sh(run):
    """SH coefficients of 1e20 (degree 2): colours ~1e20 stay finite and match the reference
    relative to their size."""
    R = run.size(4, 12)
    density, _ = random_grid(run.rng, (R, R, R), degree=2, dens=4.0)
    sh = (run.rng.choice([-1.0, 1.0], (R, R, R, 27)) * 1e20).astype(np.float32)
    o, d = random_rays(run.rng, run.size(32, 256))
    check_render(run, "1e20", density, sh, UNIT, o, d, grads=True, scale=1e20)


def sh3_poles(run):
    """SH degree 3 with view directions exactly at the poles (+-z) and next to them."""
    R = run.size(4, 12)
    density, sh = random_grid(run.rng, (R, R, R), degree=3, dens=4.0)
    g = make_grid(run, density, sh)
    for sign in (+1, -1):
        o, d = axis_rays(run.size(12, 128), 2, sign, rng=run.rng)
        check_render(run, f"dir {sign:+d}z", density, sh, UNIT, o, d, grads=True, grid=g)
        d2 = d.copy()
        d2[:, 0] = 1e-30
        d2[:, 1] = -1e-7
        check_render(run, f"dir {sign:+d}z tilted", density, sh, UNIT, o, d2, grads=True, grid=g)


def bad_inputs(run):
    """NaN / +-Inf in any input array is rejected at the API boundary with a ValueError naming
    the argument."""
    R = 3
    density, sh = random_grid(run.rng, (R, R, R), degree=0, dens=2.0)
    g = make_grid(run, density, sh)
    o, d = random_rays(run.rng, 4)
    gr = np.ones((4, 3), np.float32)
    for v in (np.nan, np.inf, -np.inf):
        tag = f"{v}"

        def poke(a, idx=(1, 1)):
            a = a.copy()
            a[idx] = v
            return a
        run.raises(f"origins {tag}", lambda: clrf.render_rays(g, poke(o), d), "origins")
        run.raises(f"dirs {tag}", lambda: clrf.render_rays(g, o, poke(d)), "dirs")
        run.raises(f"backward origins {tag}",
                   lambda: clrf.render_rays_backward(g, poke(o), d, gr), "origins")
        run.raises(f"backward dirs {tag}",
                   lambda: clrf.render_rays_backward(g, o, poke(d), gr), "dirs")
        run.raises(f"grad_rgb {tag}", lambda: clrf.render_rays_backward(g, o, d, poke(gr)),
                   "grad_rgb")
        run.raises(f"density {tag}", lambda: clrf.SparseGrid.from_dense(
            run.device, poke(density, (1, 1, 1)), sh, UNIT), "density")
        run.raises(f"sh {tag}", lambda: clrf.SparseGrid.from_dense(
            run.device, density, poke(sh, (1, 1, 1, 0)), UNIT), "sh")
        run.raises(f"bbox {tag}", lambda: clrf.SparseGrid.from_dense(
            run.device, density, sh, poke(UNIT, (1, 2))), "bbox")
        run.raises(f"background {tag}", lambda: clrf.render_rays(g, o, d, 0.5, (1.0, v, 1.0)),
                   "background")
        run.raises(f"step {tag}", lambda: clrf.render_rays(g, o, d, v), "step")
    with warnings.catch_warnings():      # the overflowing float32 cast must not warn either
        warnings.simplefilter("error")   # (a RuntimeWarning here would fail the raises check)
        run.raises("density 1e39 (overflows float32)", lambda: clrf.SparseGrid.from_dense(
            run.device, np.full((R, R, R), 1e39), sh, UNIT), "density")
        run.raises("origins 1e39 (overflows float32)",
                   lambda: clrf.render_rays(g, np.full((4, 3), 1e39), d), "origins")


# ---- scale sweep -------------------------------------------------------------------------------
def scale_sweep(run, dm, sm):
    """Density x dm, step x sm on a random grid with mixed-sign densities: outputs and
    gradients finite; also equal to the reference (skipped in quick mode for the tiny step,
    whose float64 reference takes seconds)."""
    R = run.size(4, 8)
    density, sh = random_grid(run.rng, (R, R, R), degree=1, dens=2.0, negative_frac=0.2)
    density = (density.astype(np.float64) * dm).astype(np.float32)
    mask = np.ones(density.shape, bool)
    g = make_grid(run, density, sh, mask=mask)
    o, d = random_rays(run.rng, run.size(16, 128))
    step = 0.5 * sm
    gr = run.rng.normal(size=(len(o), 3)).astype(np.float32)
    if run.quick and sm < 1:
        out = clrf.render_rays(g, o, d, step)
        grads = clrf.render_rays_backward(g, o, d, gr, step)
    else:
        out = check_render(run, "vs ref", density, sh, UNIT, o, d, step, grads=False, mask=mask,
                           grid=g)
        grads = clrf.render_rays_backward(g, o, d, gr, step)
        wg = ref.render_backward(density, sh, UNIT, o, d, gr, step, mask=mask)
        gs = max(float(np.abs(wg["density"]).max()), 1.0)
        run.compare("vs ref grad density (normwise)", grads["density"], wg["density"], GRAD,
                    scale=gs)
        run.compare("vs ref grad sh", grads["sh"], wg["sh"], GRAD)
    run.finite("outputs", out["rgb"], out["acc"], out["depth"])
    run.finite("gradients", grads["density"], grads["sh"])
