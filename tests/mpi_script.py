"""Run under `mpirun -n N` by tests/test_mpi.py: a distributed render and backward of a random
grid; rank 0 writes what the test compares with a single-device run to an .npz.

    mpirun -n 2 python tests/mpi_script.py render OUT.npz
    mpirun -n 2 python tests/mpi_script.py fail raise|exit
"""
import sys

import numpy as np

SHAPE = (10, 7, 9)
DEGREE = 1
BBOX = np.array([[-1.0, -1.2, -0.9], [1.1, 1.0, 1.0]])
STEP = 0.5
BACKGROUND = (0.3, 0.6, 0.9)


def scene(n_rays=400, seed=3):
    """(density, sh, origins, dirs, grad_rgb): a random grid with empty voxels, rays from all
    sides (some axis-aligned, some along brick faces) and a random dL/drgb."""
    rng = np.random.default_rng(seed)
    dens = rng.uniform(-0.5, 4.0, SHAPE).astype(np.float32)
    dens[rng.random(SHAPE) < 0.25] = 0
    sh = rng.normal(0, 0.5, SHAPE + (3 * (DEGREE + 1) ** 2,)).astype(np.float32)
    sh[dens == 0] = 0
    o = rng.uniform(-2.5, 2.5, (n_rays, 3))
    d = rng.uniform(-1, 1, (n_rays, 3)) - 0.4 * o
    o[:4] = [[-2, 0.05, 0.1], [0.2, -2, 0.1], [0.1, 0.3, 3], [-2, -2.1, 0.3]]
    d[:4] = [[1, 0, 0], [0, 1, 0], [0, 0, -1], [1, 1, 0]]
    g = rng.normal(size=(n_rays, 3))
    return dens, sh, o.astype(np.float32), d.astype(np.float32), g.astype(np.float32)


def render(out):
    import pyopencl.array as cla

    import clrf
    from clrf.grid.distributed import DistGrid, world
    from clrf.grid import bricks

    comm = world()
    assert comm is not None, "run under mpirun with more than one process"
    dev = clrf.Device()
    dens, sh, o, d, g = scene()
    bl = bricks.split(SHAPE, comm.Get_size())
    me = bl[comm.Get_rank()]
    dg = DistGrid(comm, bricks.BrickGrid.from_dense(dev, dens, sh, BBOX, me), bl)
    q = dev.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    comp, packed = dg.forward(od, dd, STEP, BACKGROUND)
    gd = cla.zeros(q, dg.grid.density.shape[0], np.float32)
    gs = cla.zeros(q, dg.grid.sh.shape, np.float32)
    dg.backward(od, dd, STEP, BACKGROUND, packed, comp, g, gd, gs)
    dg.sum_halo(gd, gs)
    # test only: every rank's dense gradient of the voxels it holds, gathered on rank 0; the
    # overlap voxels must agree between holders (checked by the test)
    ld, ls = dg.grid.rows_to_dense(gd.get(), gs.get())
    held = comm.gather((me.lo, me.local_hi, ld, ls), root=0)
    if comm.Get_rank() == 0:
        arrays = {"rgb": comp["rgb"], "depth": comp["depth"], "acc": comp["acc"]}
        for i, (lo, hi, a, b) in enumerate(held):
            arrays[f"lo{i}"], arrays[f"hi{i}"] = np.array(lo), np.array(hi)
            arrays[f"gd{i}"], arrays[f"gs{i}"] = a, b
        np.savez(out, **arrays)


def upsample(out, new_reso):
    """Distributed prune + resample of the random grid to new_reso ("X,Y,Z"); rank 0 writes
    the pruning weights' inputs and the merged new grid (dense density, sh, allocation)."""
    from clrf.grid.config import GridConfig
    from clrf.grid.distributed import world
    from clrf.grid import bricks
    from clrf.grid.dist_model import DistGridModel

    import clrf
    comm = world()
    dev = clrf.Device()
    dens, sh, o, d, _ = scene()
    new_reso = tuple(int(x) for x in new_reso.split(","))
    cfg = GridConfig(reso=[list(SHAPE), list(new_reso)], upsample_at=[1], sh_degree=DEGREE,
                     step=STEP, weight_thresh=UPSAMPLE_WEIGHT_THRESH * new_reso[2])
    bl = bricks.split(SHAPE, comm.Get_size())
    bg = bricks.BrickGrid.from_dense(dev, dens, sh, BBOX, bl[comm.Get_rank()])
    model = DistGridModel(dev, cfg, comm, bg, bl, BACKGROUND)
    model.upsample(o, d)
    g = model.grid
    own = g.links.get()[g.brick.own_slices]
    ld, ls = g.rows_to_dense(g.density.get(), g.sh.get())
    held = comm.gather((g.brick.lo, g.brick.hi, own >= 0, ld[g.brick.own_slices],
                        ls[g.brick.own_slices]), root=0)
    if comm.Get_rank() == 0:
        D = np.zeros(new_reso, np.float32)
        S = np.zeros(new_reso + (sh.shape[-1],), np.float32)
        A = np.zeros(new_reso, bool)
        for lo, hi, a, x, y in held:
            s = tuple(slice(p, q) for p, q in zip(lo, hi))
            A[s], D[s], S[s] = a, x, y
        np.savez(out, density=D, sh=S, alloc=A)


def fail(how):
    """Rank 1 fails alone while rank 0 waits for it in a collective: by an uncaught exception
    (how="raise") or by the CLI's way, an error printed and exit status 2 (how="exit")."""
    from clrf.runtime.mpi import end_job_if_failed, world
    comm = world()
    if comm.Get_rank() == 1:
        if how == "raise":
            raise RuntimeError("rank 1 fails alone")
        print("clrf: error: rank 1 fails alone", file=sys.stderr)
        end_job_if_failed(2)
        sys.exit(2)
    comm.barrier()


# pruning threshold of the upsample case: keeps 15 of 478 rows, 133 after dilation; no max
# weight within 3e-3 of it, so float32 weights decide as the float64 reference does
UPSAMPLE_WEIGHT_THRESH = 0.2


if __name__ == "__main__":
    {"render": render, "upsample": upsample, "fail": fail}[sys.argv[1]](*sys.argv[2:])
