"""Gaussian splats over MPI ranks (clrf/splat/distributed.py): `mpirun -n 2|3` runs of
tests/mpi_splat_script.py (the Gaussians split over the ranks, one camera per rank rendered by
its owner, the gradients sent back) against one process on the same device. Skips when mpirun
or mpi4py is missing (install: `bash tools/setup.sh test,mpi`)."""
import numpy as np
import pytest

from clrf.splat.strategies import DefaultStrategy
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


def test_training_steps_equal_one_process(tmp_path):
    """Six steps of 2 ranks (a batch of two views, each rank a shard) against one process
    taking the same batches (the mean gradient of the two views, rates times sqrt(2)): the
    same losses, parameters and density statistics."""
    from clrf.testing.tolerances import DIST_TRAIN_RTOL
    out = tmp_path / "t.npz"
    mpirun(2, SCRIPT, "train", str(out))
    r = np.load(out)
    np.testing.assert_allclose(r["losses"], r["losses1"], rtol=DIST_TRAIN_RTOL)
    assert r["losses"][-1] < r["losses"][0]
    for k in [k[3:] for k in r.files if k.startswith("p1_")]:
        one = r[f"p1_{k}"]
        # Adam's first steps are about lr * sign(gradient): one rounding to the other sign
        # moves a parameter 2 lr (<= 2 * sqrt(2) * 1.6e-2 here) apart
        np.testing.assert_allclose(r[f"p_{k}"], one, rtol=0, atol=0.05)
        assert np.mean(r[f"p_{k}"] == one) > 0.99, k
    np.testing.assert_allclose(r["stats"], r["stats1"], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("ranks", [2, 3])
def test_rebalance_keeps_the_table(tmp_path, ranks):
    """Shards of 70 / 30 % (60 / 30 / 10 %) evened out: the same table in the same order,
    each row's statistics with it."""
    out = tmp_path / "b.npz"
    mpirun(ranks, SCRIPT, "rebalance", str(out))
    r = np.load(out)
    assert r["counts"].max() - r["counts"].min() <= 1 and r["counts"].sum() == 1000
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(r[f"after_{k}"], r[f"before_{k}"])
    np.testing.assert_array_equal(r["stats"], r["stats0"])


TRAIN = ["--model", "splat", "--max-seconds", "600", "--set", "train.eval_every=1e6",
         "--set", "train.eval_views=2", "--set", "splat.densify_min_steps=5",
         "--set", "splat.densify_every=0.1", "--set", "splat.densify_from=0.05",
         "--set", "splat.densify_grad_threshold=1e-5"]


@pytest.mark.slow
def test_clrf_train_splat_over_ranks(tmp_path):
    """`mpirun -n 2 clrf train --model splat` with densification on each shard: a file per
    rank and the manifest; one process evaluates it and exports every Gaussian to one PLY;
    3 ranks and one process resume it."""
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    from clrf.splat.files import read_splat_file
    run = tmp_path / "run"
    p = mpirun(2, "-m", "clrf.cli", "train", "--out", str(run), *TRAIN,
               "--set", "train.max_iters=30")
    assert p.stdout.count('"iteration": 30') == 1      # one result line: rank 0's
    assert "Gaussians over 2 ranks" in p.stderr, p.stderr
    names = sorted(x.name for x in run.glob(checkpoint.BRICK_GLOB))
    assert names == [checkpoint.brick_file_name(30, r, 2) for r in range(2)]
    st = checkpoint.load(run)
    n = int(st["param_means"].shape[0])
    shards = [checkpoint.load(run, brick=(r, 2))["param_means"].shape[0] for r in range(2)]
    assert sum(shards) == n > 5000                        # densified from the 5,000 first
    assert all(st[k].shape == (n,) for k in DefaultStrategy.row_keys())
    assert cli(["eval", "--ckpt", str(run)]) == 0
    assert cli(["export", "--ckpt", str(run), "--splats", str(tmp_path / "s.ply")]) == 0
    assert read_splat_file(tmp_path / "s.ply")["means"].shape[0] == n
    mpirun(3, "-m", "clrf.cli", "train", "--out", str(run), "--resume", "--max-seconds", "600",
           "--set", "train.max_iters=33")
    assert checkpoint.load(run)["iteration"] == 33
    assert sorted(x.name for x in run.glob(checkpoint.BRICK_GLOB)) == [
        checkpoint.brick_file_name(33, r, 3) for r in range(3)]
    assert cli(["train", "--out", str(run), "--resume", "--max-seconds", "600",
                "--set", "train.max_iters=35"]) == 0
    assert checkpoint.load(run)["iteration"] == 35
    assert not list(run.glob(checkpoint.BRICK_GLOB)) and not list(run.glob("*.tmp*"))


@pytest.mark.slow
def test_splat_corrections_over_ranks_are_refused(tmp_path):
    """splat.pose_opt is not split over ranks: exit 2 naming the setting, nothing written."""
    p = mpirun(2, "-m", "clrf.cli", "train", "--out", str(tmp_path / "run"), *TRAIN,
               "--set", "splat.pose_opt=true", check=False)
    assert p.returncode != 0
    assert "splat.pose_opt" in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_killed_splat_rank_keeps_the_checkpoint(tmp_path):
    """SIGKILL one rank while it writes its shard: mpirun ends the job naming the signal, the
    manifest still names a complete set of shard files, and one process evaluates it."""
    import sys
    from clrf.cli.main import main as cli
    from clrf.outputs import checkpoint
    from test_mpi import DELAYED_CLI, MPIRUN, kill_a_rank_mid_write
    out = tmp_path / "run"
    kill_a_rank_mid_write([MPIRUN, "--oversubscribe", "--allow-run-as-root", "-n", "2",
                           sys.executable, "-c", DELAYED_CLI, "0.5", "train", "--out", str(out),
                           *TRAIN, "--set", "train.max_iters=100000",
                           "--set", "train.checkpoint_every=0.2"], out)
    st = checkpoint.load(out)          # the manifest's shards, joined
    n = st["param_means"].shape[0]
    assert st["iteration"] > 0 and all(st[k].shape == (n,) for k in DefaultStrategy.row_keys())
    assert cli(["eval", "--ckpt", str(out), "--max-views", "1"]) == 0
