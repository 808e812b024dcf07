"""Forward-facing (NDC) training schedule: the preset keeps the z-resolution fixed and prunes
without dilation; GridModel.upsample honours prune_dilate (checked against the float64
reference of pruning and resampling)."""
import numpy as np
import pytest

import clrf
from clrf.grid import ops as grid_ops
from clrf.references import reference as ref
from clrf.training.config import build_config
from clrf.grid.config import GridConfig
from clrf.grid.model import GridModel

BBOX = np.array([[-1.0] * 3, [1.0] * 3])


def test_forward_facing_preset_schedule():
    cfg = build_config(dataset_preset="forward_facing")
    zs = {r[2] for r in cfg.grid.reso}
    assert len(zs) == 1, "NDC stages share one z-resolution (samples per ray stay constant)"
    assert cfg.grid.reso[-1][0] > cfg.grid.reso[0][0]
    assert cfg.grid.prune_dilate is False and cfg.train.eval_downscale > 1
    syn = build_config(dataset_preset="synthetic")
    assert syn.grid.prune_dilate is True and syn.train.eval_downscale == 1


@pytest.mark.parametrize("dilate", [True, False])
def test_upsample_honours_prune_dilate(device, dilate):
    rng = np.random.default_rng(7)
    shape, new = (6, 6, 6), (12, 12, 6)
    dens = rng.uniform(0.1, 2.0, shape).astype(np.float32)
    alloc = rng.random(shape) >= 0.3
    dens[~alloc] = 0
    sh = np.zeros(shape + (3,), np.float32)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=alloc)
    o = rng.normal(0, 2.5, (300, 3)).astype(np.float32)
    d = (rng.uniform(-0.5, 0.5, (300, 3)) - o).astype(np.float32)
    mw = grid_ops.max_weight(grid, o, d, 0.5)
    mw_dense = grid.rows_to_dense(mw.get(), np.zeros((mw.shape[0], 3), np.float32))[0]
    thr = float(np.quantile(mw_dense[alloc], 0.7))
    cfg = GridConfig(reso=[list(shape), list(new)], upsample_at=[1], sh_degree=0,
                     weight_thresh=thr * new[2], prune_dilate=dilate)
    model = GridModel(device, cfg, grid, (1.0, 1.0, 1.0))
    model.upsample(o, d)
    keep = ref.prune_keep(alloc, mw_dense, dens, thr, dilate=dilate)
    _, _, want = ref.resample(dens, sh, keep, new)
    assert model.grid.reso == new and model.grid.n_rows == int(want.sum())
    assert 0 < keep.sum() < alloc.sum()
