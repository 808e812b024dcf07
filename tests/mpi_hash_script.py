"""Run under `mpirun -n N` by tests/test_mpi_hash.py: the hash grid's data-parallel step
(clrf/runtime/dataparallel.py) against the same model in one process, on every rank's device.
Rank 0 writes what the test compares to an .npz.

    mpirun -n 2 python tests/mpi_hash_script.py grad OUT.npz [RAYS]
    mpirun -n 2 python tests/mpi_hash_script.py steps OUT.npz
"""
import sys

import numpy as np

BBOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
NEAR, FAR = 1.5, 5.5
BACKGROUND = (0.2, 0.5, 0.8)
STEPS = 6           # "steps": training steps, the occupancy grid updated at 2 and 4


def rays(n, seed=5):
    """(origins, dirs, colours) float32 [n, 3]: rays from a sphere of radius 3.5 toward
    jittered points of the box, a few along the axes, random target colours."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 3.5 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.8, 0.8, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = min(n, 3)
    o[:k] = [[-3.5, 0.01, 0.02], [0.03, 3.5, -0.01], [0.0, 0.0, -3.5]][:k]
    d[:k] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]][:k]
    return (o.astype(np.float32), d.astype(np.float32),
            rng.uniform(0, 1, (n, 3)).astype(np.float32))


def model(dev):
    from clrf.hash.config import HashConfig
    from clrf.hash.model import HashModel
    cfg = HashConfig.from_preset("tiny", log2_table=12, max_res=64, samples=48, occ_res=16,
                                 occ_warmup=2, occ_every=2, occ_points=512, batch_samples=0,
                                 perturb=False, lr_schedule="steps")
    return HashModel(dev, cfg, NEAR, FAR, BBOX, BACKGROUND, seed=11)


def grads(m, o, d, c, it=0):
    """(loss, live, dL/dnet, dL/dtable) of one batch on model m (its ranks: summed)."""
    import pyopencl.array as cla
    q = m.device.queue
    args = [cla.to_device(q, a) for a in (o, d, c)]
    if m.ranks is None:
        loss, live = m.loss_and_grad(it, *args, jitter=False)
    else:
        loss, live = m._rank_loss_and_grad(it, *args, None)
    return float(loss), int(live), m.net.grad.get(), m.enc.grad.get()


def main(what, out, n=700):
    import hashlib

    import pyopencl.array as cla

    import clrf
    from clrf.runtime.dataparallel import DataParallel
    from clrf.runtime.mpi import world

    comm = world()
    assert comm is not None, "run under mpirun with more than one process"
    rank = comm.Get_rank()
    dev = clrf.Device()
    o, d, c = rays(int(n))
    res = {}
    dist = model(dev)
    dist.ranks = DataParallel(comm)
    if what == "grad":
        loss, live, gn, gt = grads(dist, o, d, c)
        res.update(loss=loss, live=live, net=gn, table=gt)
        if rank == 0:   # the same model in one process, on the same device
            loss, live, gn, gt = grads(model(dev), o, d, c)
            res.update(loss1=loss, live1=live, net1=gn, table1=gt)
    else:
        q = dev.queue
        args = [cla.to_device(q, a) for a in (o, d, c)]
        res["losses"] = [float(dist.train_step(it, *args)) for it in range(STEPS)]
        res["batch_rays"] = dist.batch_rays
        if rank == 0:
            one = model(dev)
            res["losses1"] = [float(one.train_step(it, *args)) for it in range(STEPS)]
            res["table1"], res["net1"] = one.enc.table.get(), one.net.params.get()
            res["occ1"] = one.occ.ema.get()
        res["table"], res["net"] = dist.enc.table.get(), dist.net.params.get()
        res["occ"] = dist.occ.ema.get()
    # every rank's parameters (or gradients) hashed: the ranks must hold the same bits
    keys = ("net", "table") if what == "grad" else ("net", "table", "occ")
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(res[k]).tobytes()
                                     for k in keys)).hexdigest()
    digests = comm.gather(digest, root=0)
    sent = comm.gather(dist.ranks.bytes_sent, root=0)
    if rank == 0:
        res.update(digests=np.array(digests), sent=np.array(sent))
        np.savez(out, **res)


if __name__ == "__main__":
    main(*sys.argv[1:])
