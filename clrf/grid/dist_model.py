"""DistGridModel: GridModel's training interface over the bricks of a distributed grid (one
brick per MPI rank; clrf/grid/bricks.py, clrf/grid/distributed.py).

Every rank runs the same training loop on the same batches; per step it renders its partials,
exchanges them (Allgather), composes the rays, takes the loss on the composed colours (every
rank gets the same value), runs the backward over its own brick, sums the overlap rows'
gradients with its neighbours and steps the optimisers on its own rows (the overlap replicas
get identical updates). TV and sparsity use the single grid's cell window, each brick over its
own voxels. No early termination (T_STOP 0): a brick cannot know the transmittance in front of
it during its forward march.

Checkpoints: the trainer has each rank write its brick's ``state_dict`` to its own file and
rank 0 a manifest naming them, with the layout from ``checkpoint_layout`` (the file names and
the write protocol are clrf/outputs/checkpoint.py's; this model names no file).
``checkpoint.load`` merges a manifest's bricks into one grid, so a single
process renders and evaluates a distributed run when it fits, and a distributed resume slices
its bricks from that merged grid.

Coarse-to-fine: at each scheduled iteration the grid is pruned and resampled across bricks and
split again at the new resolution, balanced by the rows the pruned grid will have
(clrf/grid/dist_ops.py). Between upsamples the bricks stay as they are.
"""
from __future__ import annotations

import numpy as np

from ..corrections import Corrections
from ..interface import StateError, Unsupported
from ..runtime.optim import Optimizer
from ..runtime.programs import device_zeros, download, upload
from . import bricks as B
from .distributed import DistGrid
from .grid import sh_dim
from .model import GridModel
from .render import BETA_EPS


class BrickMismatchError(StateError):
    """A rank's brick file does not hold the brick this rank count gives it."""


def check_schedule(cfg, ranks: int):
    """Every resolution of the schedule must split into ``ranks`` bricks (ValueError with the
    fix otherwise)."""
    for r in cfg.grid.reso[:len(cfg.grid.upsample_at) + 1]:
        B.split(r, ranks)


def initial_brick(device, cfg, bbox, brick) -> B.BrickGrid:
    """The brick's part of GridModel's first grid (clrf/grid/model.py initial_grid): constant
    density, grey colour, optionally only voxels inside the inscribed ellipsoid; the mask is
    evaluated on the brick's voxels only."""
    reso = tuple(cfg.reso[0])
    sl = brick.local_slices
    if cfg.sphere_bound:
        c = [((np.arange(r) + 0.5) / r * 2 - 1)[s] for r, s in zip(reso, sl)]
        x, y, z = np.meshgrid(*c, indexing="ij")
        mask = x * x + y * y + z * z <= 1.0
    else:
        mask = np.ones(brick.local_reso, bool)
    n = int(mask.sum())
    links = np.full(brick.local_reso, -1, np.int32)
    links[mask] = np.arange(n, dtype=np.int32)
    g = B.SparseGrid.from_arrays(device, links, np.full(n, cfg.init_density, np.float32),
                                 np.zeros((n, sh_dim(cfg.sh_degree)), np.float32), bbox)
    return B.BrickGrid.from_grid(g, brick)


class DistGridModel(GridModel):
    """GridModel over one brick per rank: the learning-rate schedule, the TV window and the
    upsample schedule are GridModel's; the step, prune/upsample, render and state are the
    bricks' own."""
    kind = "grid"

    def __init__(self, device, cfg, comm, bgrid, bricks, background, stage=0, opt_state=None):
        self.device = device
        self.cfg = cfg
        self.comm = comm
        self.bricks = bricks
        self.background = tuple(float(b) for b in background)
        self.stage = stage
        self.bg_model = None        # the bricks carry no background model (the CLI refuses one)
        # nor per-image corrections (clrf/grid/kind.py Distributed.check refuses them); the
        # empty list GridModel's hooks (on_iteration, describe) call
        self.corrections = Corrections()
        self.progress = 0.0         # the budget fraction reached (GridModel.on_iteration)
        self.dist = DistGrid(comm, bgrid, bricks)
        self._set_grid(bgrid, opt_state)

    @classmethod
    def create(cls, device, cfg, bbox, background, comm):
        bl = B.split(cfg.reso[0], comm.Get_size())
        return cls(device, cfg, comm, initial_brick(device, cfg, bbox, bl[comm.Get_rank()]), bl,
                   background)

    @classmethod
    def from_state_dict(cls, device, state, cfg, comm):
        """The rank's brick from its own brick file's state (checkpoint.load with brick=, same
        rank count) or from a whole-grid state (a merged manifest or a single-process
        checkpoint, sliced), optimiser state included."""
        links = np.asarray(state["links"])
        if "brick" in state:     # this rank's own file; the manifest lists every brick
            reso = tuple(state["brick"]["reso"])
            bl = (B.from_boxes(state["bricks"], reso) if "bricks" in state
                  else B.split(reso, comm.Get_size()))
            br = bl[comm.Get_rank()]
            if [list(br.lo), list(br.hi)] != [state["brick"]["lo"], state["brick"]["hi"]]:
                raise BrickMismatchError(
                    f"brick file of rank {comm.Get_rank()} holds {state['brick']['lo']}.."
                    f"{state['brick']['hi']}, but this split gives {br.lo}..{br.hi}")
            local = links
        else:
            bl = B.split(links.shape, comm.Get_size())
            br = bl[comm.Get_rank()]
            local = links[br.local_slices]
        rows = local[local >= 0]
        new = np.full(local.shape, -1, np.int32)
        new[local >= 0] = np.arange(rows.size, dtype=np.int32)
        g = B.SparseGrid.from_arrays(device, new, state["density"][rows], state["sh"][rows],
                                     state["bbox"])
        q = device.queue
        pad = g.density.shape[0] - rows.size
        od = np.concatenate([state["opt_density"][rows], np.zeros(pad, np.float32)])
        osh = np.concatenate([state["opt_sh"][rows], np.zeros((pad, g.sh_dim), np.float32)])
        opt = {"density": upload(q, od.astype(np.float32)),
               "sh": upload(q, osh.astype(np.float32))}
        return cls(device, cfg, comm, B.BrickGrid.from_grid(g, br), bl, state["background"],
                   int(state["stage"]), opt)

    def _set_grid(self, bgrid, opt_state=None):
        self.grid = bgrid
        self.dist.set_grid(bgrid)
        st = opt_state or {}
        self.opt_density = Optimizer(self.device, bgrid.density, self.cfg.optimizer,
                                     self.cfg.rms_beta, state=st.get("density"))
        self.opt_sh = Optimizer(self.device, bgrid.sh, self.cfg.optimizer, self.cfg.rms_beta,
                                state=st.get("sh"))
        self.touched = device_zeros(self.device.queue, bgrid.density.shape[0], np.uint8)

    # ---- training ----------------------------------------------------------------------
    def train_step(self, it, origins, dirs, target) -> float:
        """One step on a batch (device arrays [B, 3], the same on every rank); returns the
        batch MSE of the composed colours (the same on every rank)."""
        c = self.cfg
        n = origins.shape[0]
        comp, packed = self.dist.forward(origins, dirs, c.step, self.background)
        diff = comp["rgb"] - target.get().astype(np.float64)
        sq = float(np.sum(diff * diff))
        g = (2.0 / (3 * n)) * diff
        gT = None
        if c.lambda_beta:
            T = comp["T_end"]
            gT = (c.lambda_beta / n) * (1.0 / (T + BETA_EPS) - 1.0 / (1.0 - T + BETA_EPS))
        self.dist.backward(origins, dirs, c.step, self.background, packed, comp, g,
                           self.opt_density.grad, self.opt_sh.grad, self.touched, gT)
        if not (c.tv_early_only and self.stage > 0):
            self._tv(it)
        self.dist.sum_halo(self.opt_density.grad, self.opt_sh.grad, self.touched)
        lr_d, lr_s = self.learning_rates(it)
        self.opt_density.step(self.touched, lr_d, clear_touched=False)
        self.opt_sh.step(self.touched, lr_s, clear_touched=True, columns=self.sh_columns())
        return sq / (3 * n)

    def _tv_cells(self):
        return self.grid.march_reso    # the single grid's cells: the same window on every rank

    @staticmethod
    def _tv_grad(*args):
        B.tv_grad_brick(*args)

    def upsample(self, origins, dirs):
        """GridModel.upsample across the bricks (clrf/grid/dist_ops.py)."""
        from .dist_ops import upsample
        new_reso = tuple(self.cfg.reso[self.stage + 1])
        nb, bgrid, before, kept = upsample(self, origins, dirs, new_reso)
        self.bricks = nb
        self.dist.bricks = nb
        self._set_grid(bgrid)
        self.stage += 1
        return (f"pruned {before} -> {kept} rows, upsampled to {new_reso[0]}x{new_reso[1]}x"
                f"{new_reso[2]} in {len(nb)} bricks")

    # ---- evaluation (collective: every rank calls it with the same rays) ----------------
    def _render_chunk(self, o, d):
        """GridModel.render's chunks, composed over the bricks."""
        return self.dist.forward(o, d, self.cfg.step, self.background)[0]

    def ray_loss_grad(self, origins, dirs, target):
        """Refused: a ray's camera gradient would need every brick's share of it (a test view's
        pose is refined on a whole grid: `clrf eval` loads the checkpoint in one process)."""
        raise Unsupported("the distributed grid cannot refine a camera's pose over its bricks; "
                          "run `clrf eval --refine-poses` in one process")

    def describe(self):
        r = self.grid.march_reso
        own = self.grid.links.get()[self.grid.brick.own_slices]
        rows = self.comm.allreduce(int(np.count_nonzero(own >= 0)))
        return f"{r[0]}x{r[1]}x{r[2]} grid, {rows} rows in {len(self.bricks)} bricks"

    # ---- state -------------------------------------------------------------------------
    def state_dict(self):
        g = self.grid
        n = g.n_rows
        b = g.brick
        return {
            "kind": "grid", "stage": self.stage, "sh_degree": g.sh_degree,
            "background": list(self.background), "bbox": g.bbox,
            "links": download(g.links), "density": download(g.density)[:n],
            "sh": download(g.sh)[:n],
            "opt_density": download(self.opt_density.state)[:n],
            "opt_sh": download(self.opt_sh.state)[:n],
            "brick": {"rank": b.index, "ranks": len(self.bricks), "lo": list(b.lo),
                      "hi": list(b.hi), "reso": list(b.reso)},
        }

    def checkpoint_layout(self) -> dict:
        """The whole grid's resolution and the bricks' [lo, hi] boxes for the checkpoint's
        manifest (clrf/outputs/checkpoint.py save_distributed, which names the files)."""
        return {"reso": list(self.grid.march_reso),
                "bricks": [[list(b.lo), list(b.hi)] for b in self.bricks]}
