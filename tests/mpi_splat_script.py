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
    proj, seen, counts, _ = D.gather_records(comm, rast, shard, cams)
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


def train(out, steps=6):
    """`train`: DistSplatModel on the procedural scene for a few steps against one process
    doing the same batches (each step the mean gradient of P views, rates times sqrt(P))."""
    import clrf
    from clrf.data.synthetic import load_procedural
    from clrf.runtime.mpi import world
    from clrf.splat.distributed import DistSplatModel
    from clrf.splat.model import camera_of
    from clrf.splat.strategies import RenderInfo
    from clrf.training.config import build_config

    comm = world()
    P, r = comm.Get_size(), comm.Get_rank()
    dev = clrf.Device()
    ds = load_procedural(n_train=16, n_test=2, size=40)
    cfg = build_config("procedural", overrides={
        "train": {"model": "splat"}, "splat": {"init": "random", "init_points": 300}})
    from clrf.splat.model import create_model
    dist = create_model(dev, cfg, ds, (0.0, 0.0, 0.0), cls=DistSplatModel)
    dist._join_ranks(comm, dist.max_count).take_shard()
    losses = [dist.train_step(it) for it in range(int(steps))]
    shards = comm.gather((dist.host_params(), dist.strategy.host_rows()), root=0)
    if r:
        return
    one = create_model(dev, cfg, ds, (0.0, 0.0, 0.0))
    one.lr_scale = float(np.sqrt(P))
    losses1 = []
    for it in range(int(steps)):
        total, mse = None, 0.0
        for k in range(P):
            v = one.view_of(it * P + k)
            cam = camera_of(ds.poses[v], ds.intrinsics, ds.hw)
            params = one._rparams()
            proj, bins, ras = one.rast.forward(params, cam, one.background)
            grad, stats = one._loss().loss_and_grad(ras.rgb, one._target(v))
            mse += one._loss_fn.read(stats)["mse"] / P
            absgrad = one.strategy.absgrad
            g2d = one.rast.rasterize_backward(proj, bins, ras, cam, grad, one.background,
                                              absgrad=absgrad)
            grads = one.rast.project_backward(params, cam, g2d)
            one.strategy.step_post_backward(
                one.params, grads, one.moments, one.step,
                RenderInfo(proj.radius, g2d["xy_abs" if absgrad else "xy"], cam.width,
                           cam.height))
            if total is None:
                total = grads
            else:
                for name in total:
                    total[name] += grads[name]
        for name in total:
            total[name] *= np.float32(1.0 / P)
        one.step += 1
        one._adam(total, one.step)
        losses1.append(mse)
    res = {"losses": np.array(losses), "losses1": np.array(losses1)}
    for name, v in one.host_params().items():
        res[f"p1_{name}"] = v
        res[f"p_{name}"] = np.concatenate([s[0][name] for s in shards])
    rows = one.strategy.ROWS
    res["stats1"] = np.stack([one.strategy.host_rows()[k] for k in rows])
    res["stats"] = np.stack([np.concatenate([s[1][k] for s in shards]) for k in rows])
    np.savez(out, **res)


if __name__ == "__main__" and sys.argv[1] == "train":
    train(*sys.argv[2:])
    sys.exit(0)


def rebalance(out):
    """`rebalance`: shards of 70 % and 30 % (2 ranks; 3 ranks: 60, 30, 10 %) evened out;
    rank 0 writes the joined table before and after and the counts after."""
    import clrf
    from clrf.data.synthetic import load_procedural
    from clrf.runtime.mpi import world
    from clrf.splat.distributed import DistSplatModel
    from clrf.splat.model import create_model
    from clrf.training.config import build_config

    comm = world()
    P, r = comm.Get_size(), comm.Get_rank()
    dev = clrf.Device()
    ds = load_procedural(n_train=4, n_test=1, size=24)
    cfg = build_config("procedural", overrides={
        "train": {"model": "splat"}, "splat": {"init": "random", "init_points": 1000}})
    m = create_model(dev, cfg, ds, (0.0, 0.0, 0.0), cls=DistSplatModel)
    m._join_ranks(comm, m.max_count)
    whole = m.host_params()
    m.strategy.rows["grad_accum"].set(np.arange(m.n, dtype=np.float32))   # the statistics
    mom, stats = m.host_moments(), m.strategy.host_rows()                # move with their rows
    cuts = np.round(np.cumsum([0] + ([0.7, 0.3] if P == 2 else [0.6, 0.3, 0.1])) * m.n)
    lo, hi = int(cuts[r]), int(cuts[r + 1])
    m._release()
    m._set_host({k: v[lo:hi] for k, v in whole.items()}, {k: v[lo:hi] for k, v in mom.items()},
                {k: v[lo:hi] for k, v in stats.items()})
    counts = comm.allgather(m.n)
    m.rebalance(counts)
    after = comm.gather((m.host_params(), m.strategy.host_rows()), root=0)
    if r == 0:
        res = {"counts": np.array([a[0]["means"].shape[0] for a in after]),
               "stats": np.stack([np.concatenate([a[1][k] for a in after]) for k in stats]),
               "stats0": np.stack(list(stats.values()))}
        for k, v in whole.items():
            res[f"before_{k}"] = v
            res[f"after_{k}"] = np.concatenate([a[0][k] for a in after])
        np.savez(out, **res)


if __name__ == "__main__" and sys.argv[1] == "rebalance":
    rebalance(*sys.argv[2:])
    sys.exit(0)


if __name__ == "__main__" and sys.argv[1] not in ("train", "rebalance"):
    main(*sys.argv[1:])
