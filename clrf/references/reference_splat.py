"""Float64 numpy twins of the Gaussian-splatting kernels (cl/splat_project.cl,
cl/splat_raster.cl): projection and its backward, binning as per-tile sorted lists, the tile
compositing forward and its backward; the test oracle, not on any runtime path.

The constants are the float32 values the kernels are built with (clrf/splat/raster.py passes
them as defines): ALPHA_MAX = float32(0.99) and T_MIN = float32(1e-4) decide, e.g., whether a
pixel behind two clamped Gaussians stops (T = (1 - 0.99)^2 sits on T_MIN), so the twin uses the
same numbers. Everything else is float64.

Shapes: n Gaussians; params dict(means [n, 3], log_scales [n, 3], quats [n, 4] (w, x, y, z),
opacity_logits [n], sh [n, B, 3]); cam dict(viewmat [4, 4] world-to-camera, fx, fy, cx, cy,
width, height, near). Projected splats dict(xy [n, 2], conic [n, 3], radius [n], depth [n],
color [n, 3], opacity [n], rect [n, 4], visible [n]).
"""
from __future__ import annotations

import numpy as np

from .reference import sh_basis, sh_dir_grad

TILE = 16
ALPHA_MAX = float(np.float32(0.99))
ALPHA_MIN = float(np.float32(1.0 / 255.0))
T_MIN = float(np.float32(1e-4))
COV_DILATION = float(np.float32(0.3))
AA_FILTER2D = float(np.float32(0.1))   # the anti-aliased projection's 2D filter
FRUSTUM_GUARD = float(np.float32(1.3))
SIGMA_RADIUS = 3.0
FILTER3D_VAR = float(np.float32(0.2))
FILTER3D_MARGIN = float(np.float32(0.15))


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera [4, 4] of a camera at ``eye`` looking at ``target`` (x right, y down,
    z forward; ``up`` is the world direction that appears upwards, i.e. along -y)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    V = np.eye(4)
    V[:3, :3], V[:3, 3] = R, -R @ eye
    return V


def quat_rot(q) -> np.ndarray:
    """Rotation matrices [n, 3, 3] of unit quaternions q [n, 4] (w, x, y, z)."""
    w, x, y, z = (q[:, k] for k in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def tiles(cam, tile=TILE):
    return -(-int(cam["width"]) // tile), -(-int(cam["height"]) // tile)


def tile_rect(xy, radius, ntx, nty, tile=TILE) -> np.ndarray:
    """Tile rectangles [n, 4] (x0, y0, x1, y1) of the squares xy +- radius, in the dtype of xy
    (float32 inputs: the kernel's exact arithmetic); zero radius -> empty."""
    xy = np.asarray(xy)
    r = np.asarray(radius)[:, None]
    with np.errstate(invalid="ignore", over="ignore"):
        lo = np.floor((xy - r) / tile)
        hi = np.floor((xy + r) / tile) + 1
    lim = np.array([ntx, nty], xy.dtype)
    lo, hi = np.clip(lo, 0, lim), np.clip(hi, 0, lim)
    rect = np.concatenate([lo, hi], 1).astype(np.int64)
    rect[np.asarray(radius) <= 0] = 0
    return rect


def _intermediates(params, cam):
    """Everything the projection computes (as cl/splat_project.cl splat_project_one). With
    ``params["filter3d"]`` (f2 [n], the 3D filter's variance) the anti-aliased projection
    (ANTIALIASED=1): scales widened to se = sqrt(s^2 + f2), opacity factors c3 and c2, and the
    2D filter ``params.get("filter2d", AA_FILTER2D)`` px^2 in place of COV_DILATION."""
    m = np.asarray(params["means"], np.float64)
    ls = np.asarray(params["log_scales"], np.float64)
    q = np.asarray(params["quats"], np.float64)
    V = np.asarray(cam["viewmat"], np.float64)
    R, t = V[:3, :3], V[:3, 3]
    fx, fy = float(cam["fx"]), float(cam["fy"])
    n = m.shape[0]
    I = {"R": R, "fx": fx, "fy": fy}
    tc = m @ R.T + t
    qq = np.sum(q * q, 1)
    vis = (tc[:, 2] > cam["near"]) & (qq > 0)
    qlen = np.sqrt(qq)
    qn = np.where(vis[:, None], q / np.where(qlen > 0, qlen, 1)[:, None], [1.0, 0, 0, 0])
    s = np.exp(ls)
    aa = params.get("filter3d") is not None
    dil = float(np.float32(params.get("filter2d", AA_FILTER2D))) if aa else COV_DILATION
    f2 = np.asarray(params["filter3d"], np.float64) if aa else np.zeros(n)
    se = np.sqrt(s * s + f2[:, None]) if aa else s
    c3 = np.prod(s / se, 1) if aa else np.ones(n)
    Rq = quat_rot(qn)
    S3 = np.einsum("nik,nk,njk->nij", Rq, se * se, Rq)
    z = np.where(vis, tc[:, 2], 1.0)
    lim_x = FRUSTUM_GUARD * 0.5 * cam["width"] / fx
    lim_y = FRUSTUM_GUARD * 0.5 * cam["height"] / fy
    ux, uy = tc[:, 0] / z, tc[:, 1] / z
    clamp_x, clamp_y = np.abs(ux) > lim_x, np.abs(uy) > lim_y
    rx, ry = np.clip(ux, -lim_x, lim_x), np.clip(uy, -lim_y, lim_y)
    J = np.zeros((n, 2, 3))
    J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * rx / z
    J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * ry / z
    Tm = J @ R
    Vm = Tm @ S3
    with np.errstate(over="ignore", invalid="ignore"):
        S2 = Vm @ np.transpose(Tm, (0, 2, 1))
        a = S2[:, 0, 0] + dil
        b = S2[:, 0, 1]
        c = S2[:, 1, 1] + dil
        sc = np.maximum(a, c)
        an, bn, cn = a / sc, b / sc, c / sc
        detn = an * cn - bn * bn
        dn = dil / sc
        det0n = (an - dn) * (cn - dn) - bn * bn
        c2 = (np.where((det0n > 0) & (detn > 0), np.sqrt(np.abs(det0n / detn)), 0.0) if aa
              else np.ones(n))
        vis &= np.isfinite(a) & np.isfinite(b) & np.isfinite(c) & (detn > 0)
        inv = np.where(vis, 1.0 / np.where(vis, detn * sc, 1.0), 0.0)
        conic = np.stack([cn * inv, -bn * inv, an * inv], 1)
        vis &= np.all(np.isfinite(conic), 1)
        lam = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
        radius = np.where(vis, SIGMA_RADIUS * np.sqrt(np.where(vis, lam, 0.0)), 0.0)
    xy = np.stack([fx * tc[:, 0] / z + cam["cx"], fy * tc[:, 1] / z + cam["cy"]], 1)
    I.update(aa=aa, dil=dil, f2=f2, se=se, c3=c3, c2=c2, sc=sc, a=a, b=b, c=c, detn=detn,
             det0n=det0n)
    I.update(tc=tc, vis=vis, qn=qn, qlen=qlen, s=s, Rq=Rq, S3=S3, z=z, rx=rx, ry=ry,
             clamp_x=clamp_x, clamp_y=clamp_y, Tm=Tm, Vm=Vm, conic=conic, xy=xy, radius=radius)
    return I


def filter3d(means, cams) -> np.ndarray:
    """Each Gaussian's 3D filter variance f2 [n] over the training cameras ``cams`` (camera
    dicts): FILTER3D_VAR (min t_z / fx)^2 over the cameras that see its mean (t_z > near, the
    projection within FILTER3D_MARGIN of the image); -1 where none does (splat_filter3d)."""
    m = np.asarray(means, np.float64)
    best = np.full(m.shape[0], np.inf)
    for cam in cams:
        V = np.asarray(cam["viewmat"], np.float64)
        tc = m @ V[:3, :3].T + V[:3, 3]
        z = tc[:, 2]
        front = z > cam["near"]
        zs = np.where(front, z, 1.0)
        u = cam["fx"] * tc[:, 0] / zs + cam["cx"]
        v = cam["fy"] * tc[:, 1] / zs + cam["cy"]
        w, h, k = cam["width"], cam["height"], FILTER3D_MARGIN
        seen = front & (u >= -k * w) & (u <= (1 + k) * w) & (v >= -k * h) & (v <= (1 + k) * h)
        best = np.where(seen, np.minimum(best, zs / cam["fx"]), best)
    return np.where(np.isfinite(best), FILTER3D_VAR * best * best, -1.0)


def _view_dirs(means, cam):
    V = np.asarray(cam["viewmat"], np.float64)
    pos = -V[:3, :3].T @ V[:3, 3]
    v = np.asarray(means, np.float64) - pos
    dist = np.linalg.norm(v, axis=1)
    return v / np.where(dist > 0, dist, 1.0)[:, None], dist


def _raw_color(params, cam):
    sh = np.asarray(params["sh"], np.float64)
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    dirs, dist = _view_dirs(params["means"], cam)
    Y = sh_basis(dirs, degree)
    return 0.5 + np.einsum("nb,nbc->nc", Y, sh), Y, dirs, dist, degree


def sigmoid(x):
    x = np.asarray(x, np.float64)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def project(params, cam, tile=TILE) -> dict:
    """The projected splats (module docstring); culled Gaussians are all zeros."""
    I = _intermediates(params, cam)
    vis = I["vis"]
    col, *_ = _raw_color(params, cam)
    ntx, nty = tiles(cam, tile)
    out = {"xy": I["xy"], "conic": I["conic"], "radius": I["radius"], "depth": I["tc"][:, 2],
           "color": np.maximum(col, 0.0),
           "opacity": sigmoid(np.asarray(params["opacity_logits"], np.float64))
           * I["c3"] * I["c2"]}
    for k in out:
        out[k] = np.where(vis.reshape((-1,) + (1,) * (out[k].ndim - 1)), out[k], 0.0)
    out["rect"] = tile_rect(out["xy"], out["radius"], ntx, nty, tile)
    out["visible"] = vis
    return out


def bin_gaussians(rect, depth, ntx, nty) -> list:
    """Per tile (id ty * ntx + tx), the Gaussian ids whose rect covers it, sorted front to back
    by depth, equal depths by id (the kernel's stable sort of the emit order)."""
    rect = np.asarray(rect)
    lists = [[] for _ in range(ntx * nty)]
    for i, (x0, y0, x1, y1) in enumerate(rect):
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                lists[ty * ntx + tx].append(i)
    depth = np.asarray(depth)
    return [np.array(sorted(ids, key=lambda i: (depth[i], i)), np.int64) for ids in lists]


def _tile_alpha(proj, ids, px, py):
    """For pixel centres (px, py) [P] and list ids [K]: alpha (0 where skipped), raw o G, G,
    d [P, K, 2]."""
    pix = np.stack([px + 0.5, py + 0.5], 1)
    d = np.asarray(proj["xy"], np.float64)[ids][None] - pix[:, None]
    A, B, C = (np.asarray(proj["conic"], np.float64)[ids, k][None] for k in range(3))
    power = -0.5 * (A * d[..., 0] ** 2 + C * d[..., 1] ** 2) - B * d[..., 0] * d[..., 1]
    G = np.exp(power)
    raw = np.asarray(proj["opacity"], np.float64)[ids][None] * G
    alpha = np.minimum(ALPHA_MAX, raw)
    alpha = np.where((power > 0) | (alpha < ALPHA_MIN), 0.0, alpha)
    return alpha, raw, G, d


def _tile_pixels(t, ntx, width, height, tile):
    ty, tx = divmod(t, ntx)
    ys, xs = np.meshgrid(np.arange(ty * tile, min((ty + 1) * tile, height)),
                         np.arange(tx * tile, min((tx + 1) * tile, width)), indexing="ij")
    return xs.ravel(), ys.ravel()


def rasterize(proj, lists, width, height, background=(0.0, 0.0, 0.0), tile=TILE) -> dict:
    """dict(rgb [H, W, 3], T [H, W], n_contrib [H, W], depth [H, W]: sum_k T_k alpha_k z_k of
    the splats' camera depths, cl/splat_raster.cl RENDER_DEPTH) of the per-tile lists (front
    to back)."""
    bg = np.asarray(background, np.float64)
    ntx = -(-width // tile)
    rgb = np.zeros((height, width, 3))
    T_out = np.ones((height, width))
    n_out = np.zeros((height, width), np.int64)
    d_out = np.zeros((height, width))
    col = np.asarray(proj["color"], np.float64)
    z = np.asarray(proj["depth"], np.float64)
    for t, ids in enumerate(lists):
        px, py = _tile_pixels(t, ntx, width, height, tile)
        T = np.ones(px.size)
        C = np.zeros((px.size, 3))
        D = np.zeros(px.size)
        last = np.zeros(px.size, np.int64)
        if ids.size:
            alpha = _tile_alpha(proj, ids, px, py)[0]
            done = np.zeros(px.size, bool)
            for k in range(ids.size):
                a = alpha[:, k]
                act = ~done & (a > 0)
                nT = T * (1 - a)
                stop = act & (nT < T_MIN)
                done |= stop
                act &= ~stop
                C[act] += (a * T)[act, None] * col[ids[k]]
                D[act] += (a * T)[act] * z[ids[k]]
                T = np.where(act, nT, T)
                last = np.where(act, k + 1, last)
                if done.all():
                    break
        rgb[py, px] = C + T[:, None] * bg
        T_out[py, px] = T
        n_out[py, px] = last
        d_out[py, px] = D
    return {"rgb": rgb, "T": T_out, "n_contrib": n_out, "depth": d_out}


def rasterize_backward(proj, lists, fwd, width, height, grad_rgb, background=(0.0, 0.0, 0.0),
                       tile=TILE) -> dict:
    """dL/d(xy, conic, opacity, color) of the compositing for dL/drgb ``grad_rgb`` [H, W, 3]
    (the derivation is in cl/splat_raster.cl's header), and "xy_abs": the per-pixel terms of
    dL/dxy summed in absolute value (ABSGRAD); ``fwd`` is rasterize's output."""
    bg = np.asarray(background, np.float64)
    n = np.asarray(proj["xy"]).shape[0]
    g = {"xy": np.zeros((n, 2)), "conic": np.zeros((n, 3)), "opacity": np.zeros(n),
         "color": np.zeros((n, 3)), "xy_abs": np.zeros((n, 2))}
    col = np.asarray(proj["color"], np.float64)
    conic = np.asarray(proj["conic"], np.float64)
    ntx = -(-width // tile)
    grad_rgb = np.asarray(grad_rgb, np.float64)
    for t, ids in enumerate(lists):
        if not ids.size:
            continue
        px, py = _tile_pixels(t, ntx, width, height, tile)
        alpha, raw, G, d = _tile_alpha(proj, ids, px, py)
        npix = fwd["n_contrib"][py, px]
        T = np.asarray(fwd["T"], np.float64)[py, px].copy()
        gp = grad_rgb[py, px]
        S = np.tile(bg, (px.size, 1))
        for k in range(ids.size - 1, -1, -1):
            a = alpha[:, k]
            act = (k < npix) & (a > 0)
            if not act.any():
                continue
            i = ids[k]
            T = np.where(act, T / (1 - a), T)
            dalpha = np.where(act, T * np.sum(gp * (col[i] - S), 1), 0.0)
            S = np.where(act[:, None], a[:, None] * col[i] + (1 - a[:, None]) * S, S)
            g["color"][i] += np.sum(np.where(act, T * a, 0.0)[:, None] * gp, 0)
            free = act & (raw[:, k] < ALPHA_MAX)
            dpow = np.where(free, raw[:, k] * dalpha, 0.0)
            g["opacity"][i] += np.sum(np.where(free, G[:, k] * dalpha, 0.0))
            dx, dy = d[:, k, 0], d[:, k, 1]
            A, B, C = conic[i]
            gx, gy = -dpow * (A * dx + B * dy), -dpow * (B * dx + C * dy)
            g["xy"][i] += [np.sum(gx), np.sum(gy)]
            g["xy_abs"][i] += [np.sum(np.abs(gx)), np.sum(np.abs(gy))]
            g["conic"][i] += [np.sum(-0.5 * dpow * dx * dx), np.sum(-dpow * dx * dy),
                              np.sum(-0.5 * dpow * dy * dy)]
    return g


def project_backward(params, cam, grads2d) -> dict:
    """dL/d(means, log_scales, quats, opacity_logits, sh) from dL/d(xy, conic, color, opacity)
    of the projected splats (derivation: cl/splat_project.cl's header)."""
    return _backward(params, cam, grads2d)[0]


def camera_backward(params, cam, grads2d) -> dict:
    """Each Gaussian's share of dL/dR [n, 3, 3] and dL/dt [n, 3] of the camera's world-to-camera
    transform ``viewmat`` = [R t] (zeros for culled Gaussians; sum over the Gaussians for the
    camera's gradient), as cl/splat_project.cl's backward with POSE_GRAD=1:
    dL/dR = g_t m^T + J^T dL/dT + t g_dir^T, dL/dt = g_t + R g_dir."""
    _, part = _backward(params, cam, grads2d)
    I, gt, dT, g_dir = part["I"], part["gt"], part["dT"], part["g_dir"]
    m = np.asarray(params["means"], np.float64)
    R, z = I["R"], I["z"]
    t = np.asarray(cam["viewmat"], np.float64)[:3, 3]
    n = m.shape[0]
    J = np.zeros((n, 2, 3))
    J[:, 0, 0], J[:, 0, 2] = I["fx"] / z, -I["fx"] * I["rx"] / z
    J[:, 1, 1], J[:, 1, 2] = I["fy"] / z, -I["fy"] * I["ry"] / z
    dR = (gt[:, :, None] * m[:, None, :] + np.transpose(J, (0, 2, 1)) @ dT
          + t[None, :, None] * g_dir[:, None, :])
    dt = gt + g_dir @ R.T
    vis = I["vis"]
    return {"R": np.where(vis[:, None, None], dR, 0.0), "t": np.where(vis[:, None], dt, 0.0)}


def _backward(params, cam, grads2d):
    """(project_backward's dict, its intermediates: I, gt = dL/dt_c, dT = dL/dT, g_dir)."""
    I = _intermediates(params, cam)
    vis = I["vis"]
    R, fx, fy = I["R"], I["fx"], I["fy"]
    tc, z = I["tc"], I["z"]
    gxy = np.asarray(grads2d["xy"], np.float64)
    gq = np.asarray(grads2d["conic"], np.float64)
    gcol = np.asarray(grads2d["color"], np.float64)
    gop = np.asarray(grads2d["opacity"], np.float64)
    sh = np.asarray(params["sh"], np.float64)
    # colour
    col, Y, dirs, dist, degree = _raw_color(params, cam)
    gc = np.where(col < 0, 0.0, gcol)
    d_sh = Y[:, :, None] * gc[:, None, :]
    w = np.einsum("nc,nbc->nb", gc, sh)
    gdir = sh_dir_grad(dirs, w, degree)
    gm = (gdir - dirs * np.sum(dirs * gdir, 1, keepdims=True)) / np.where(dist > 0, dist,
                                                                          1)[:, None]
    g_dir = gm
    # opacity
    o = sigmoid(np.asarray(params["opacity_logits"], np.float64))
    c3, c2 = I["c3"], I["c2"]
    d_logit = gop * c3 * c2 * o * (1 - o)
    g_c = gop * o                        # dL/d(c3 c2) (ANTIALIASED)
    # mean in pixels
    gt = np.stack([gxy[:, 0] * fx / z, gxy[:, 1] * fy / z,
                   -(gxy[:, 0] * fx * tc[:, 0] + gxy[:, 1] * fy * tc[:, 1]) / z ** 2], 1)
    # conic -> Sigma2 -> (T, Sigma3)
    A, B, C = I["conic"][:, 0], I["conic"][:, 1], I["conic"][:, 2]
    Q = np.stack([np.stack([A, B], -1), np.stack([B, C], -1)], 1)
    GQ = np.stack([np.stack([gq[:, 0], gq[:, 1] / 2], -1),
                   np.stack([gq[:, 1] / 2, gq[:, 2]], -1)], 1)
    GS = -Q @ GQ @ Q
    GS = 0.5 * (GS + np.transpose(GS, (0, 2, 1)))
    if I["aa"]:   # c2 = sqrt(det0 / det1) through Sigma2's entries (b counts twice)
        with np.errstate(divide="ignore", invalid="ignore"):
            sc, detn, det0n = I["sc"], I["detn"], I["det0n"]
            an, bn, cn, dn = I["a"] / sc, I["b"] / sc, I["c"] / sc, I["dil"] / sc
            g2 = np.where(c2 > 0, g_c * c3 * 0.5 * c2 / sc, 0.0)
            live = c2 > 0
            GS[:, 0, 0] += np.where(live, g2 * ((cn - dn) / det0n - cn / detn), 0.0)
            GS[:, 1, 1] += np.where(live, g2 * ((an - dn) / det0n - an / detn), 0.0)
            off = np.where(live, g2 * (-bn / det0n + bn / detn), 0.0)
            GS[:, 0, 1] += off
            GS[:, 1, 0] += off
    Tm, Vm = I["Tm"], I["Vm"]
    dT = 2 * GS @ Vm
    G3 = np.transpose(Tm, (0, 2, 1)) @ GS @ Tm
    dJ = dT @ R.T
    gt[:, 2] += -fx / z ** 2 * dJ[:, 0, 0] - fy / z ** 2 * dJ[:, 1, 1]
    gt[:, 0] += np.where(I["clamp_x"], 0.0, -fx / z ** 2 * dJ[:, 0, 2])
    gt[:, 2] += np.where(I["clamp_x"], 1.0, 2.0) * fx * I["rx"] / z ** 2 * dJ[:, 0, 2]
    gt[:, 1] += np.where(I["clamp_y"], 0.0, -fy / z ** 2 * dJ[:, 1, 2])
    gt[:, 2] += np.where(I["clamp_y"], 1.0, 2.0) * fy * I["ry"] / z ** 2 * dJ[:, 1, 2]
    gm = gm + gt @ R
    # Sigma3 = M M^T, M = Rq diag(s)
    Rq, s, se = I["Rq"], I["s"], I["se"]
    M = Rq * se[:, None, :]
    dM = 2 * G3 @ M
    # the covariance's share through se (= s without the filter) and c3's
    d_ls = np.sum(dM * Rq, 1) * s * s / se
    if I["aa"]:
        d_ls = d_ls + (g_c * c2 * c3)[:, None] * I["f2"][:, None] / (se * se)
    dR = dM * se[:, None, :]
    qw, qx, qy, qz = (I["qn"][:, k] for k in range(4))
    g = lambda j, k: dR[:, j, k]  # noqa: E731
    gqn = 2 * np.stack([
        -qz * g(0, 1) + qy * g(0, 2) + qz * g(1, 0) - qx * g(1, 2) - qy * g(2, 0) + qx * g(2, 1),
        qy * g(0, 1) + qz * g(0, 2) + qy * g(1, 0) - 2 * qx * g(1, 1) - qw * g(1, 2)
        + qz * g(2, 0) + qw * g(2, 1) - 2 * qx * g(2, 2),
        -2 * qy * g(0, 0) + qx * g(0, 1) + qw * g(0, 2) + qx * g(1, 0) + qz * g(1, 2)
        - qw * g(2, 0) + qz * g(2, 1) - 2 * qy * g(2, 2),
        -2 * qz * g(0, 0) - qw * g(0, 1) + qx * g(0, 2) + qw * g(1, 0) - 2 * qz * g(1, 1)
        + qy * g(1, 2) + qx * g(2, 0) + qy * g(2, 1)], 1)
    qn = I["qn"]
    d_q = (gqn - qn * np.sum(qn * gqn, 1, keepdims=True)) / np.where(vis, I["qlen"], 1)[:, None]
    out = {"means": gm, "log_scales": d_ls, "quats": d_q, "opacity_logits": d_logit,
           "sh": d_sh}
    for k in out:
        out[k] = np.where(vis.reshape((-1,) + (1,) * (out[k].ndim - 1)), out[k], 0.0)
    return out, {"I": I, "gt": gt, "dT": dT, "g_dir": g_dir}


def render(params, cam, background=(0.0, 0.0, 0.0), tile=TILE):
    """(projected splats, per-tile lists, rasterize's dict) of the float64 chain."""
    proj = project(params, cam, tile)
    ntx, nty = tiles(cam, tile)
    lists = bin_gaussians(proj["rect"], proj["depth"], ntx, nty)
    return proj, lists, rasterize(proj, lists, int(cam["width"]), int(cam["height"]),
                                  background, tile)


def render_backward(params, cam, grad_rgb, background=(0.0, 0.0, 0.0), tile=TILE) -> dict:
    """dL/d(params) of the whole chain for dL/drgb ``grad_rgb``, plus "grad2d"."""
    proj, lists, fwd = render(params, cam, background, tile)
    g2d = rasterize_backward(proj, lists, fwd, int(cam["width"]), int(cam["height"]), grad_rgb,
                             background, tile)
    out = project_backward(params, cam, g2d)
    out["grad2d"] = g2d
    return out
