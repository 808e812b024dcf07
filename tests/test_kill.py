"""SIGKILL safety: `clrf train` killed at random moments, one of them inside a checkpoint write,
always leaves a checkpoint that `clrf eval` loads, and `--resume` continues from it with
metrics.csv intact (rows up to the checkpoint kept, rows after it dropped, no duplicates).

The moment inside the checkpoint write is made deterministic by the process the test starts
(DELAYED_CLI): it sets clrf.outputs.checkpoint.WRITE_DELAY, so checkpoint.save pauses that long
after writing the temporary file and before renaming it, and the test kills while the temporary
file exists.
"""
import csv
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clrf.outputs import checkpoint
from clrf.cli.main import main as cli

ROOT = Path(__file__).resolve().parent.parent
TINY = ["--set", "grid.reso=[[12,12,12],[24,24,24]]", "--set", "grid.upsample_at=[6]",
        "--set", "grid.batch_size=512", "--set", "train.eval_every=0.4",
        "--set", "train.eval_views=1", "--set", "train.checkpoint_every=0.3"]
TIMEOUT = 90
# `clrf ARGS` with checkpoint writes held open for the seconds of the first argument:
# python -c DELAYED_CLI SECONDS ARGS...
DELAYED_CLI = ("import sys; from clrf.outputs import checkpoint; "
               "checkpoint.WRITE_DELAY = float(sys.argv.pop(1)); "
               "from clrf.cli import main; sys.exit(main())")


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))[1:]


def _temps(out):
    return [p.name for p in out.iterdir() if ".tmp" in p.name]


def _scene(path):
    """A small .npz scene (16 views of 16x16 pixels): quick to load in every new process."""
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (16, 1, 1))
    poses[:, 0, 3] = np.linspace(-0.5, 0.5, 16)
    poses[:, 2, 3] = 4.0
    np.savez(path, images=rng.uniform(size=(16, 16, 16, 3)).astype(np.float32), poses=poses,
             focal=20.0)
    return path


def _start(out, resume, delay, data=None, options=TINY):
    env = dict(os.environ)   # the installed clrf (tests/conftest.py)
    args = ["--resume"] if resume else ["--data", str(data), *options]
    return subprocess.Popen([sys.executable, "-c", DELAYED_CLI, str(delay), "train", "--out",
                             str(out), "--max-seconds", "600", *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _wait_for(p, cond, what):
    t0 = time.time()
    while not cond():
        assert p.poll() is None, f"train exited early ({what}): {p.stderr.read().decode()}"
        assert time.time() - t0 < TIMEOUT, f"timed out waiting for {what}"
        time.sleep(0.02)


def _ckpt_iteration(out):
    try:
        return int(checkpoint.load(out)["iteration"])
    except checkpoint.CheckpointError:
        return -1


@pytest.mark.slow
def test_sigkill_at_random_moments_keeps_a_resumable_run(tmp_path, capsys):
    out = tmp_path / "run"
    data = _scene(tmp_path / "scene.npz")
    rng = random.Random(1234)
    kept = []           # metrics rows a resume must preserve, in order
    plan = ["random", "checkpoint-write", "random", "checkpoint-write"]
    for k, moment in enumerate(plan):
        delay = 1.0 if moment == "checkpoint-write" else 0.0
        p = _start(out, resume=k > 0, delay=delay, data=data)
        try:
            before = _ckpt_iteration(out)
            # let the run write (another) checkpoint beyond the one it resumed from
            _wait_for(p, lambda: _ckpt_iteration(out) > before, "a new checkpoint")
            if moment == "checkpoint-write":
                _wait_for(p, lambda: any(n.startswith("ckpt.npz.tmp") for n in _temps(out)),
                          "a checkpoint write")
            else:
                time.sleep(rng.uniform(0.0, 1.5))
        finally:
            p.send_signal(signal.SIGKILL)
            p.wait(timeout=30)
        if moment == "checkpoint-write":
            assert any(n.startswith("ckpt.npz.tmp") for n in _temps(out)), "missed the window"

        # the last complete checkpoint loads and evaluates
        it = _ckpt_iteration(out)
        assert it > 0
        capsys.readouterr()
        assert cli(["eval", "--ckpt", str(out), "--max-views", "1",
                    "--out", str(tmp_path / f"eval{k}.json")]) == 0, capsys.readouterr().err
        # the rows the checkpoint vouches for; later (or half-written) rows belong to lost work
        rows = _rows(out / "metrics.csv")
        assert rows[:len(kept)] == kept, "rows up to an earlier checkpoint were lost"
        kept = [r for r in rows if len(r) > 1 and r[0].isdigit() and int(r[0]) <= it]

    # a final resume runs to the end of a short budget
    budget = float(checkpoint.load(out)["seconds"]) + 1.0
    it = _ckpt_iteration(out)
    capsys.readouterr()
    assert cli(["train", "--out", str(out), "--resume", "--max-seconds", str(budget)]) == 0, \
        capsys.readouterr().err
    assert not _temps(out), f"temporary files left behind: {_temps(out)}"
    rows = _rows(out / "metrics.csv")
    assert rows[:len(kept)] == kept
    new = rows[len(kept):]
    assert new and all(int(r[0]) > it for r in new), "resume must append after the checkpoint"
    iters = [int(r[0]) for r in rows]
    assert iters == sorted(iters), f"iterations out of order: {iters}"
    assert len({tuple(r) for r in rows}) == len(rows), "duplicated rows"
    # one periodic row per iteration, plus the final-evaluation row at the last iteration
    periodic = [int(r[0]) for r in rows if r[2]]
    assert len(periodic) == len(set(periodic)), f"duplicated iterations: {periodic}"
    assert int(checkpoint.load(out)["iteration"]) > it


SPLAT = ["--model", "splat", "--set", "splat.preset=tiny", "--set", "splat.init_points=300",
         "--set", "train.eval_every=0.4", "--set", "train.eval_views=1",
         "--set", "train.checkpoint_every=0.2"]


@pytest.mark.slow
def test_sigkill_inside_a_splat_checkpoint_write_keeps_the_last_one(tmp_path, capsys):
    """The splat model's checkpoint (Gaussians, Adam moments, densification statistics) under
    SIGKILL inside its write: the previous checkpoint loads, evaluates, and resumes to the end
    of a short budget, leaving no temporary file."""
    out = tmp_path / "run"
    data = _scene(tmp_path / "scene.npz")
    p = _start(out, resume=False, delay=1.0, data=data, options=SPLAT)
    try:
        _wait_for(p, lambda: _ckpt_iteration(out) > 0, "a first checkpoint")
        _wait_for(p, lambda: any(n.startswith("ckpt.npz.tmp") for n in _temps(out)),
                  "a checkpoint write")
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(timeout=30)
    assert any(n.startswith("ckpt.npz.tmp") for n in _temps(out)), "missed the window"
    state = checkpoint.load(out)
    it = int(state["iteration"])
    assert it > 0 and state["kind"] == "splat" and len(state["param_means"]) > 0
    capsys.readouterr()
    assert cli(["eval", "--ckpt", str(out), "--max-views", "1",
                "--out", str(tmp_path / "eval.json")]) == 0, capsys.readouterr().err
    budget = float(state["seconds"]) + 1.0
    assert cli(["train", "--out", str(out), "--resume", "--max-seconds", str(budget)]) == 0, \
        capsys.readouterr().err
    assert not _temps(out), f"temporary files left behind: {_temps(out)}"
    after = checkpoint.load(out)
    assert int(after["iteration"]) > it and after["kind"] == "splat"


def test_trim_metrics_drops_later_and_torn_rows(tmp_path):
    from clrf.outputs.rundir import remove_stale_temps, trim_metrics
    from clrf.training.trainer import CSV_FIELDS
    f = tmp_path / "metrics.csv"
    good = ["0,0.0,,,9.1,0.5,1,,m\r\n", "5,1.0,0.1,10,9.5,0.6,1,100,m\r\n"]
    later = "9,2.0,0.1,10,9.9,0.7,1,100,m\r\n"
    f.write_bytes(("iteration,seconds,train_loss,train_psnr,eval_psnr,eval_ssim,eval_views,"
                   "rays_per_s,model\r\n" + "".join(good) + later + "12,2.5,0.0").encode())
    assert trim_metrics(f, CSV_FIELDS, 5) == 2
    assert _rows(f) == [r.strip().split(",") for r in good]
    assert trim_metrics(f, CSV_FIELDS, 5) == 0
    for name in ("ckpt.npz.tmp4242", "error_vs_time.png.tmp.png", "eval.json.tmp",
                 ".config.json.tmp"):
        (tmp_path / name).write_text("x")
    assert len(remove_stale_temps(tmp_path)) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.csv"]
