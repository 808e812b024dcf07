"""Float64 twin of cl/splat_exposure.cl (the colour transform per training image: the splat
model's whole images, the hash model's ray batches) and the evaluation protocol of NeRF in the
Wild for captures with changing exposure: fit a transform on the left half of a test image,
score the right half.

Row v of P [V, 12]: A (3 x 3, row-major), then b (3); out = A rgb + b per pixel.
"""
from __future__ import annotations

import numpy as np

ROW = 12
MEAN_ITERATIONS = 20   # recentre's fixed-point iterations (a few reach 1e-13 near the identity)
IDENTITY = np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0], np.float64)
# splat.exposure_matrix / hash.exposure_matrix, in the order of their kernel argument
# ``matrix``: "full" trains every entry; "diagonal" A's diagonal and b (a gain and an offset
# per channel); "gain" A's diagonal only (a gain per channel: exposure and white balance)
MATRICES = ("full", "diagonal", "gain")
TRAINED = (np.ones(ROW, bool),
           np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1], bool),
           np.array([1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0], bool))
TRAINED_DIAGONAL = TRAINED[1]


def split(row):
    """(A [3, 3], b [3]) of a 12-float row."""
    row = np.asarray(row, np.float64)
    return row[:9].reshape(3, 3), row[9:12]


def apply(rgb, P, v, clip=False):
    """out [n, 3] = A_v rgb + b_v for rgb [n, 3]; clip: clamped to [0, 1], as a camera clips."""
    A, b = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    out = np.asarray(rgb, np.float64).reshape(-1, 3) @ A.T + b
    return np.clip(out, 0.0, 1.0) if clip else out


def shown(c, T, background, P, v, masked=True, clip=False):
    """What the loss sees of a pixel of premultiplied colour c [n, 3], transmittance T [n] on
    ``background``: A c + (1 - T) b + T bg for a masked (RGBA) capture, whose background the
    exposure leaves alone; A (c + T bg) + b without alpha; clip: clamped to [0, 1]."""
    A, b = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    T = np.asarray(T, np.float64).reshape(-1, 1)
    c = np.asarray(c, np.float64).reshape(-1, 3)
    bg = np.asarray(background, np.float64)[:3]
    out = (c + T * bg) @ A.T + b if not masked else c @ A.T + (1 - T) * b + T * bg
    return np.clip(out, 0.0, 1.0) if clip else out


def render_background(P, v, background, masked=True):
    """The background bg' to render with, so that A (c + T bg') + b is ``shown``:
    A^-1 (bg - b) for a masked capture, else bg."""
    bg = np.asarray(background, np.float64)[:3]
    if not masked:
        return bg
    A, b = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    return np.linalg.solve(A, bg - b)


def rays_behind(P, index, pixels, background):
    """[n, 3]: each ray's background A_v^-1 (bg - b_v) of its row v = index // pixels (a masked
    capture on a renderer that composites the background itself; cl/splat_exposure.cl
    exposure_rays_behind), bg where the row has a non-finite entry, A_v is singular (|det| <=
    1e-12) or the result is not finite."""
    bg = np.asarray(background, np.float64)[:3]
    rows = np.asarray(P, np.float64).reshape(-1, ROW)[np.asarray(index) // int(pixels)]
    out = np.tile(bg, (len(rows), 1))
    for i, row in enumerate(rows):
        A, b = split(row)
        if np.all(np.isfinite(row)) and abs(np.linalg.det(A)) > 1e-12:
            x = np.linalg.solve(A, bg - b)
            if np.all(np.isfinite(x)):
                out[i] = x
    return out


def backward(rgb, grad_out, P, v, T=None, background=None, clip=False):
    """(dL/drgb' [n, 3], dL/dP_v [12]) from dL/dout ``grad_out`` [n, 3] of out = A rgb' + b.
    A masked capture (T and its render's ``background`` bg' given): rgb' = c + T bg', bg'
    the function A^-1 (bg - b) of P (``render_background``), so dL/dA = sum g c^T and
    dL/db = sum g (1 - T). T None: a capture without alpha, dL/dA = sum g rgb'^T,
    dL/db = sum g. clip: out clamped to [0, 1]; a channel clipped there passes nothing
    (clip 1 or True), or only a g that points back inside (clip 2: g > 0 above 1, g < 0
    below 0; a surrogate, not the clamp's derivative)."""
    A, _ = split(np.asarray(P, np.float64).reshape(-1, ROW)[v])
    x = np.asarray(rgb, np.float64).reshape(-1, 3)
    g = np.asarray(grad_out, np.float64).reshape(-1, 3)
    if clip:
        out = apply(x, P, v)
        outside = (out < 0) | (out > 1)
        if clip == 2:
            outside &= ~(((out > 1) & (g > 0)) | ((out < 0) & (g < 0)))
        g = np.where(outside, 0.0, g)
    T = np.zeros(len(x)) if T is None else np.asarray(T, np.float64).reshape(-1)
    if background is not None:
        x = x - T[:, None] * np.asarray(background, np.float64)[:3]
    return g @ A, np.concatenate([(g.T @ x).ravel(), (g * (1 - T)[:, None]).sum(axis=0)])


def adam(P, m, vm, v, grad_row, lr, reg, b1, b2, eps, t, matrix=0):
    """Adam step t (1-based) of row v, with the pull 2 reg (P - I) added to ``grad_row``;
    matrix (an index of MATRICES): the entries it does not train are left as they are.
    Returns new (P, m, vm), float64 copies."""
    P = np.array(P, np.float64).reshape(-1, ROW)
    m = np.array(m, np.float64).reshape(-1, ROW)
    vm = np.array(vm, np.float64).reshape(-1, ROW)
    k = TRAINED[int(matrix)]
    g = (np.asarray(grad_row, np.float64) + 2.0 * reg * (P[v] - IDENTITY))[k]
    m[v, k] = b1 * m[v, k] + (1 - b1) * g
    vm[v, k] = b2 * vm[v, k] + (1 - b2) * g * g
    P[v, k] -= lr * (m[v, k] / (1 - b1 ** t)) / (np.sqrt(vm[v, k] / (1 - b2 ** t)) + eps)
    return P, m, vm


def _ray_terms(state, background, P, index, pixels, masked):
    """(x, y, d, A, b) of a ray batch: out = A x + y b (+ T bg masked), d = dout/dT."""
    st = np.asarray(state, np.float64).reshape(-1, 8)
    c, a = st[:, :3], st[:, 3:4]
    bg = np.asarray(background, np.float64)[:3]
    rows = np.asarray(P, np.float64).reshape(-1, ROW)[np.asarray(index) // int(pixels)]
    A, b = rows[:, :9].reshape(-1, 3, 3), rows[:, 9:]
    if masked:
        return c, a, bg - b, A, b
    return c + (1 - a) * bg, np.ones_like(a), np.einsum("nij,j->ni", A, bg), A, b


def rays(state, background, target, P, index, pixels, masked=True, clip=False):
    """(residual r = out - target [n, 3], the marcher's target eff = c - A^T r [n, 3] (its
    backward on a black background), sq = |r|^2 [n], the background's share bgt = T r.dout/dT
    [n]) of a ray batch: c, a = state[:, :3], state[:, 3] (premultiplied colour, opacity),
    T = 1 - a, out = A c + a b + T bg (masked) or A (c + T bg) + b; ray i's row is
    index[i] // pixels. ``clip``: sq of out clamped to [0, 1], and r (so eff, bgt and the
    rows' gradient) 0 in a channel where out lies outside [0, 1]."""
    x, y, d, A, b = _ray_terms(state, background, P, index, pixels, masked)
    st = np.asarray(state, np.float64).reshape(-1, 8)
    T = 1 - st[:, 3:4]
    out = np.einsum("nij,nj->ni", A, x) + y * b
    if masked:
        out = out + T * np.asarray(background, np.float64)[:3]
    t = np.asarray(target, np.float64).reshape(-1, 3)
    r = out - t
    sq = np.sum(r * r, axis=1)
    if clip:   # the loss sees the clamped colour; a clipped channel passes no gradient
        sq = np.sum((np.clip(out, 0.0, 1.0) - t) ** 2, axis=1)
        r = np.where((out < 0) | (out > 1), 0.0, r)
    eff = st[:, :3] - np.einsum("nji,nj->ni", A, r)
    return r, eff, sq, T[:, 0] * np.sum(r * d, axis=1)


def rays_loss(state, background, target, P, index, pixels, scale, masked=True, clip=False):
    """L = scale sum_i |r_i|^2 of a ray batch (``rays``; what rays_grad differentiates, the
    pull aside)."""
    return float(scale * rays(state, background, target, P, index, pixels, masked,
                              clip)[2].sum())


def rays_bg(offsets, dt, sigma, bgt, scale, dsigma):
    """dsigma [m] (a copy) with each live sample j of ray i given -2 scale dt_j bgt_i."""
    out = np.array(dsigma, np.float64)
    for i in range(len(offsets) - 1):
        for j in range(offsets[i], offsets[i + 1]):
            if sigma[j] > 0:
                out[j] -= 2.0 * scale * dt[j] * bgt[i]
    return out


def rays_grad(state, background, resid, P, index, pixels, scale, reg, masked=True,
              matrix=0):
    """dL/dP [V, 12] of rays_loss from its residuals (dL/dA = 2 s sum r x^T, dL/db =
    2 s sum y r: x = c, y = a masked, else x = c + T bg, y = 1), plus each row's pull
    2 reg (P_v - I) weighted by its share of the batch (its rays / n); ``matrix`` (an index
    of MATRICES): 0 for the entries it does not train."""
    c, a, _, _, _ = _ray_terms(state, background, P, index, pixels, masked)
    r = np.asarray(resid, np.float64).reshape(-1, 3)
    P = np.asarray(P, np.float64).reshape(-1, ROW)
    row = np.asarray(index) // int(pixels)
    g = np.zeros_like(P)
    n = len(r)
    for v in range(len(P)):
        sel = row == v
        g[v, :9] = 2.0 * scale * (r[sel].T @ c[sel]).ravel()
        g[v, 9:] = 2.0 * scale * (a[sel] * r[sel]).sum(axis=0)
        g[v] += 2.0 * reg * (sel.sum() / max(n, 1)) * (P[v] - IDENTITY)
    g[:, ~TRAINED[int(matrix)]] = 0.0
    return g


def fit_row(rgb, T, render_bg, background, target, row, reg, eta, masked=True, clip=False,
            matrix=0):
    """The row moved by ``eta`` toward the least-squares transform of a whole render (a
    Gauss-Newton step of the squared error, which is quadratic in the row): the render rgb
    [n, 3] and transmittance T [n] on ``render_bg``; masked: regress target - T bg on
    [c, 1 - T] (c = rgb - T render_bg), else target on [rgb, 1]; pulled toward the identity by
    reg n |M - I|^2 (the loss's pull, per pixel); clip: pixels with a clipped target channel
    (0 or 1: the camera's clip hides what the transform gave there) are left out; matrix (an
    index of MATRICES): "diagonal" fits each channel on its own colour and the offset, "gain"
    on its own colour only (the entries they do not train kept as they were).
    Returns the new 12-float row (float64)."""
    x = np.asarray(rgb, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    if clip:
        keep = np.all((y > 0) & (y < 1), axis=1)
        x, y = x[keep], y[keep]
        T = np.asarray(T, np.float64).reshape(-1)[keep]
    n = len(x)
    if n < 4:    # too few pixels left to fit the row's four columns
        return np.asarray(row, np.float64).copy()
    if masked:
        t = np.asarray(T, np.float64).reshape(-1, 1)
        F = np.concatenate([x - t * np.asarray(render_bg, np.float64)[:3], 1 - t], axis=1)
        y = y - t * np.asarray(background, np.float64)[:3]
    else:
        F = np.concatenate([x, np.ones((n, 1))], axis=1)
    row = np.asarray(row, np.float64)
    if int(matrix):
        fitted = row.copy()
        cols = [3] if int(matrix) == 1 else []    # the offset's column, where it trains
        for i in range(3):       # channel i on its colour (and the offset's column)
            Fi = F[:, [i] + cols]
            pull = np.array([1.0, 0.0])[:Fi.shape[1]]
            sol = np.linalg.solve(Fi.T @ Fi + reg * n * np.eye(len(pull)),
                                  Fi.T @ y[:, i] + reg * n * pull)
            fitted[4 * i] = sol[0]
            if cols:
                fitted[9 + i] = sol[1]
        return row + eta * (fitted - row)
    E = np.concatenate([np.eye(3), np.zeros((1, 3))])           # the identity, as M^T
    Mt = np.linalg.solve(F.T @ F + reg * n * np.eye(4), F.T @ y + reg * n * E)
    fitted = np.concatenate([Mt[:3].T.ravel(), Mt[3]])
    return row + eta * (fitted - row)


def affine(row) -> np.ndarray:
    """The 4 x 4 matrix [[A, b], [0, 0, 0, 1]] of a 12-float row."""
    A, b = split(row)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = A, b
    return M


def recentre(P, rows, matrix=0):
    """P [V, 12] (float64 copy) with the geometric mean G = expm(mean logm(M_v)) of the rows
    ``rows`` taken out of each of them, M_v <- M_v G^-1, so that their mean logarithm is zero
    (iterated: for matrices that do not commute one such step only nears it).
    The data cannot tell a scene x and transforms M_v from G x and M_v G^-1, so the transforms
    would otherwise drift with the scene's colours along that direction (a gauge: only their
    pull toward the identity holds it, weakly); fixed there, the scene has the images' mean
    exposure, in the geometric sense (gains 0.6 and 1.5 around 0.95, not 1.05). Returns P
    unchanged when a logarithm is not real and finite (a transform far from the identity).
    matrix (an index of MATRICES): the rows of "diagonal" and "gain" are diagonal transforms,
    whose mean is diagonal (without an offset for "gain"); the entries they do not train are
    kept exactly (at 0) instead of taking the logarithms' rounding."""
    P = np.array(P, np.float64).reshape(-1, ROW)
    out = _recentre(P.copy(), np.asarray(rows, np.int64))
    kept = ~TRAINED[int(matrix)]
    out[:, kept] = P[:, kept]
    return out


def _recentre(P, rows):
    """recentre on P (modified, returned), every entry taken as it comes out."""
    from scipy.linalg import expm, logm
    if len(rows) == 0:
        return P
    M = [affine(P[v]) for v in rows]
    for _ in range(MEAN_ITERATIONS):   # matrices do not commute: the mean's fixed point
        logs = [logm(m) for m in M]
        if not all(np.all(np.isfinite(L)) and np.abs(np.imag(L)).max() <= 1e-9
                   for L in logs):
            return P.copy() if _ == 0 else _rows_of(P, rows, M)
        mean = np.mean(np.real(logs), axis=0)
        if np.abs(mean).max() < 1e-13:
            break
        Ginv = np.linalg.inv(expm(mean))
        M = [m @ Ginv for m in M]
    return _rows_of(P, rows, M)


def _rows_of(P, rows, M):
    for v, m in zip(rows, M):
        P[v] = np.concatenate([m[:3, :3].ravel(), m[:3, 3]])
    return P


def fit_affine(render, target):
    """The 12-float row (A, b) that maps ``render`` [..., 3] closest to ``target`` in least
    squares (float64)."""
    x = np.asarray(render, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64).reshape(-1, 3)
    X = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(X, y, rcond=None)          # [4, 3]: A^T over b
    return np.concatenate([sol[:3].T.ravel(), sol[3]])


def half_fitted_psnr(render, target):
    """NeRF-W's protocol: (PSNR of the right half after the transform fitted on the left half,
    PSNR of the right half as rendered) for one image [H, W, 3] in [0, 1]."""
    render = np.asarray(render, np.float64)
    target = np.asarray(target, np.float64)
    w = render.shape[1] // 2
    row = fit_affine(render[:, :w], target[:, :w])
    right = apply(render[:, w:].reshape(-1, 3), row[None], 0).reshape(render[:, w:].shape)

    def psnr(a, b):
        mse = float(np.mean((np.clip(a, 0, 1) - b) ** 2))
        return float(-10 * np.log10(max(mse, 1e-12)))
    return psnr(right, target[:, w:]), psnr(render[:, w:], target[:, w:])


def gain_sums(render, acc, target, background, masked=True):
    """One test view's share of the shared-gain figure (``shared_gain_psnr``): [4, 3] per
    channel, the sums of x^2, x y and y^2 over its pixels and (row 3) the pixel count, where x
    is the render's light that an exposure scales and y the target's: the scene's light
    c = render - T bg and target - T bg (T = 1 - acc) for a masked capture, whose background
    the exposure leaves alone; the whole pixel without alpha."""
    r = np.asarray(render, np.float64).reshape(-1, 3)
    y = np.asarray(target, np.float64)[..., :3].reshape(-1, 3)
    if masked:
        Tbg = (1.0 - np.asarray(acc, np.float64).reshape(-1, 1)) * \
            np.asarray(background, np.float64)[:3]
        r, y = r - Tbg, y - Tbg
    return np.stack([(r * r).sum(0), (r * y).sum(0), (y * y).sum(0),
                     np.full(3, float(len(r)))])


def shared_gain_psnr(sums):
    """The gauge-free score of a run with a transform per training image: one gain per
    channel for ALL test views together (least squares over their pixels; the scene's overall
    brightness is not fixed by training images that each have their own exposure), then each
    view's PSNR under it, unclipped. ``sums``: the views' ``gain_sums``. Returns (gain [3],
    PSNR per view [n])."""
    S = np.asarray(sums, np.float64).reshape(-1, 4, 3)
    xx, xy = S[:, 0].sum(0), S[:, 1].sum(0)
    gain = np.where(xx > 0, xy / np.where(xx > 0, xx, 1.0), 1.0)
    se = (gain ** 2 * S[:, 0] - 2 * gain * S[:, 1] + S[:, 2]).sum(1)   # [n]
    mse = np.maximum(se / S[:, 3].sum(1), 1e-12)
    return gain, -10.0 * np.log10(mse)
