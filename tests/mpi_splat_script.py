"""Run under `mpirun -n N` by tests/test_mpi_splat.py: Gaussian splats split over the ranks
(clrf/splat/distributed.py), a batch of one camera per rank rendered by its owner and the
gradients sent back, against the same Gaussians and cameras in one process on the same device.
Rank 0 writes what the test compares to an .npz.

    mpirun -n 2 python tests/mpi_splat_script.py OUT.npz [N] [CAMERAS]
"""
import sys

import numpy as np

DEGREE = 2
BACKGROUND = (0.2, 0.4, 0.6)
W, H = 45, 31


def gaussians(n, seed=4):
    """n random Gaussians about the origin (float32), a few behind every camera."""
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(0, 0.6, (n, 3)).astype(np.float32),
            "log_scales": rng.uniform(-3.0, -1.2, (n, 3)).astype(np.float32),
            "quats": rng.normal(size=(n, 4)).astype(np.float32),
            "opacity_logits": rng.uniform(-2.0, 2.0, n).astype(np.float32),
            "sh": rng.normal(0, 0.3, (n, (DEGREE + 1) ** 2, 3)).astype(np.float32)}


def cameras(k):
    """k cameras on a circle about the origin, looking at it."""
    from clrf.references import reference_splat as rs
    from clrf.splat.raster import SplatCamera
    out = []
    for i in range(k):
        a = 2 * np.pi * i / k + 0.3
        eye = (3.0 * np.sin(a), 0.4 * np.cos(3 * a), -3.0 * np.cos(a))
        out.append(SplatCamera(rs.look_at(eye, (0, 0, 0)).astype(np.float32), 40.0, 42.0,
                               W / 2 - 0.5, H / 2 + 0.25, W, H, 0.1))
    return out


def grad_image(k):
    return np.random.default_rng(100 + k).normal(size=(H, W, 3)).astype(np.float32)


def one_camera(rast, params, cam, k, absgrad=True):
    """(image, dL/dparams of every Gaussian, dL/dxy_abs) of camera k in one process."""
    from clrf.runtime.programs import upload
    proj, bins, ras = rast.forward(params, cam, BACKGROUND)
    g2d = rast.rasterize_backward(proj, bins, ras, cam, upload(rast.device.queue,
                                                               grad_image(k)),
                                  BACKGROUND, absgrad=absgrad)
    grads = rast.project_backward(params, cam, g2d)
    return ras.rgb.get(), {k2: v.get() for k2, v in grads.items()}, g2d["xy_abs"].get()


def main(out, n=400, k=None):
    import clrf
    from clrf.runtime.dataparallel import DataParallel
    from clrf.runtime.mpi import world
    from clrf.runtime.programs import upload
    from clrf.splat import distributed as D
    from clrf.splat.raster import SplatRasterizer

    comm = world()
    assert comm is not None, "run under mpirun with more than one process"
    P, r = comm.Get_size(), comm.Get_rank()
    n = int(n)
    k = P if k is None else int(k)
    dev = clrf.Device()
    rast = SplatRasterizer(dev, DEGREE)
    host = gaussians(n)
    lo, hi = DataParallel(comm).share(n)
    q = dev.queue
    shard = rast.upload({name: a[lo:hi] for name, a in host.items()})
    cams = cameras(k)
    proj, seen, counts = D.gather_records(comm, rast, shard, cams)
    res = {}
    g2d = None
    if proj is not None:
        cam = cams[r]
        bins = rast.bin(proj, cam)
        ras = rast.rasterize(proj, bins, cam, BACKGROUND)
        g2d = rast.rasterize_backward(proj, bins, ras, cam, upload(q, grad_image(r)),
                                      BACKGROUND, absgrad=True)
        res["rgb"] = ras.rgb.get()
    back = D.return_grads(comm, g2d, counts, seen, hi - lo, absgrad=True)
    grads, xy_abs = None, []
    for c, g in enumerate(back[:len(cams)]):
        gd = {name: upload(q, np.ascontiguousarray(a)) for name, a in g.items()}
        out_c = rast.project_backward(shard, cams[c], gd)
        grads = {name: v.get() for name, v in out_c.items()} if grads is None else \
            {name: grads[name] + v.get() for name, v in out_c.items()}
        xy_abs.append(g["xy_abs"])
    rgbs = comm.gather(res.get("rgb"), root=0)
    shards = comm.gather((grads, xy_abs), root=0)
    render = D.allgather_records(comm, rast, shard, cams[0])
    rb = rast.bin(render, cams[0])
    rendered = rast.rasterize(render, rb, cams[0], BACKGROUND).rgb.get()
    renders = comm.gather(rendered, root=0)
    if r == 0:
        full = rast.upload(host)
        for c, cam in enumerate(cams):
            img, g1, abs1 = one_camera(rast, full, cam, c)
            res[f"rgb1_{c}"], res[f"abs1_{c}"] = img, abs1
            res[f"rgb_{c}"] = rgbs[c]
            res[f"abs_{c}"] = np.concatenate([s[1][c] for s in shards])
            for name, v in g1.items():
                res[f"g1_{name}"] = res.get(f"g1_{name}", 0) + v
        for name in shards[0][0]:
            res[f"g_{name}"] = np.concatenate([s[0][name] for s in shards])
        res["renders"] = np.stack(renders)
        np.savez(out, **res)


if __name__ == "__main__":
    main(*sys.argv[1:])
