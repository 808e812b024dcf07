"""Float64 references of cl/ray_pose.cl (rays from each image's corrected camera, the camera
gradient of a ray batch summed per image) and of the host's dL/dR, dL/dt: the test oracle, not
on any runtime path."""
from __future__ import annotations

import numpy as np


def rows(viewmats0, viewmats) -> np.ndarray:
    """[V, 12]: per image A_v = R^T R0 (row-major) and c_v = -R^T t of given world-to-camera
    viewmats0 [V, 4, 4] and corrected viewmats [V, 4, 4]."""
    V0, V = np.asarray(viewmats0, np.float64), np.asarray(viewmats, np.float64)
    R0, R, t = V0[:, :3, :3], V[:, :3, :3], V[:, :3, 3]
    A = np.einsum("vji,vjk->vik", R, R0)
    c = -np.einsum("vji,vj->vi", R, t)
    return np.concatenate([A.reshape(-1, 9), c], axis=1)


def apply(index, pixels: int, rows_, o0, d0):
    """(o [n, 3], d [n, 3]): ray i moved by its image's row (o = c_v, d = A_v d0)."""
    r = np.asarray(rows_, np.float64)[np.asarray(index) // pixels]
    d = np.einsum("nij,nj->ni", r[:, :9].reshape(-1, 3, 3), np.asarray(d0, np.float64))
    return r[:, 9:].copy(), d


def sums(index, pixels: int, d, ray_grad, n_images: int) -> np.ndarray:
    """[V, 13] = (S_d = sum_i d_i dL/dd_i^T row-major, S_o = sum_i dL/do_i, the ray count) per
    image over the batch."""
    v = np.asarray(index) // pixels
    g = np.asarray(ray_grad, np.float64)
    d = np.asarray(d, np.float64)
    out = np.zeros((n_images, 13))
    np.add.at(out, v, np.concatenate([np.einsum("na,nb->nab", d, g[:, 3:]).reshape(-1, 9),
                                      g[:, :3], np.ones((len(v), 1))], axis=1))
    return out


def camera_gradient(viewmat, s) -> tuple:
    """(dL/dR [3, 3], dL/dt [3]) of the camera ``viewmat`` [4, 4] that made the rays whose sums
    are ``s`` [13]: dL/dR = R S_d - t S_o^T, dL/dt = -R S_o."""
    V = np.asarray(viewmat, np.float64)
    R, t = V[:3, :3], V[:3, 3]
    s = np.asarray(s, np.float64)
    Sd, So = s[:9].reshape(3, 3), s[9:12]
    return R @ Sd - np.outer(t, So), -R @ So
