"""Gaussian splats over MPI ranks (clrf/splat/distributed.py): `mpirun -n 2|3` runs of
tests/mpi_splat_script.py (the Gaussians split over the ranks, one camera per rank rendered by
its owner, the gradients sent back) against one process on the same device. Skips when mpirun
or mpi4py is missing (install: `bash tools/setup.sh test,mpi`)."""
import numpy as np
import pytest

from clrf.testing.tolerances import SPLAT_GRAD_REL_TO_MAX, SPLAT_RASTER_ATOL

from test_mpi import mpirun, pytestmark  # noqa: F401 - the same skip

SCRIPT = "tests/mpi_splat_script.py"


@pytest.mark.parametrize("ranks,n,cams", [(2, 400, 2), (3, 400, 3), (3, 400, 2), (3, 5, 3)])
def test_sharded_render_and_gradients_equal_one_process(tmp_path, ranks, n, cams):
    """Each owner's image, each Gaussian's parameter gradients summed over the batch's
    cameras and its absolute screen gradients (the density statistics' input) against one
    process; also with a rank that owns no camera (3 ranks, 2 cameras) and with shards of one
    or two Gaussians (5 over 3 ranks). The collective render (every rank's records on every
    rank) gives every rank the one-process image."""
    out = tmp_path / "s.npz"
    mpirun(ranks, SCRIPT, str(out), str(n), str(cams))
    r = np.load(out)
    for c in range(cams):
        one = r[f"rgb1_{c}"]
        assert one.std() > 0.01                      # the Gaussians are in view
        np.testing.assert_allclose(r[f"rgb_{c}"], one, rtol=0, atol=SPLAT_RASTER_ATOL)
        np.testing.assert_allclose(r[f"abs_{c}"], r[f"abs1_{c}"], rtol=0,
                                   atol=SPLAT_GRAD_REL_TO_MAX * np.abs(r[f"abs1_{c}"]).max())
    names = [k[3:] for k in r.files if k.startswith("g1_")]
    assert sorted(names) == ["log_scales", "means", "opacity_logits", "quats", "sh"]
    for name in names:
        one = r[f"g1_{name}"]
        assert r[f"g_{name}"].shape == one.shape and np.count_nonzero(one) > 0
        np.testing.assert_allclose(r[f"g_{name}"], one, rtol=0,
                                   atol=SPLAT_GRAD_REL_TO_MAX * np.abs(one).max())
    assert r["renders"].shape[0] == ranks
    for img in r["renders"]:
        np.testing.assert_allclose(img, r["rgb1_0"], rtol=0, atol=SPLAT_RASTER_ATOL)
