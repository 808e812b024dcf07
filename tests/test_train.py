"""Training end to end through the CLI: outputs, resume, checkpoints, render/eval, bad input."""
import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clrf.outputs import checkpoint
from clrf.cli.main import main as cli
from clrf.training.config import ConfigError, build_config
from clrf.data.synthetic import load_procedural
from clrf.grid.model import GridModel

ROOT = Path(__file__).resolve().parent.parent
# A small, fast schedule for the built-in scene: 16^3 -> 32^3 after 8 iterations.
FAST = ["--set", "grid.reso=[[16,16,16],[32,32,32]]", "--set", "grid.upsample_at=[8]",
        "--set", "grid.batch_size=1024", "--set", "train.eval_every=1.0",
        "--set", "train.eval_views=2"]


def run_cli(*args):
    return cli([str(a) for a in args])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "r"
    rc = run_cli("train", "--out", out, "--max-seconds", 4, *FAST)
    assert rc == 0
    return out


def read_csv(p):
    return list(csv.DictReader(open(p)))


@pytest.mark.slow
def test_train_writes_every_output(trained):
    for name in ("config.json", "metrics.csv", "error_vs_time.png", "ckpt.npz", "eval.json"):
        assert (trained / name).is_file(), name
    rows = read_csv(trained / "metrics.csv")
    assert {"iteration", "seconds", "train_loss", "eval_psnr", "eval_ssim"} <= set(rows[0])
    secs = [float(r["seconds"]) for r in rows]
    assert secs == sorted(secs) and secs[-1] >= 4.0
    losses = [float(r["train_loss"]) for r in rows if r["train_loss"]]
    assert losses[-1] < 0.5 * losses[0], "training must reduce the loss"
    psnr = [float(r["eval_psnr"]) for r in rows if r["eval_psnr"]]   # (some rows: loss only)
    assert psnr[-1] > psnr[0] + 3
    cfg = json.loads((trained / "config.json").read_text())
    assert cfg["grid"]["reso"] == [[16, 16, 16], [32, 32, 32]] and cfg["train"]["preset"] == "procedural"
    ev = json.loads((trained / "eval.json").read_text())
    assert ev["n_views"] == 8 and np.isfinite(ev["psnr"])
    assert any("32x32x32" in r["model"] for r in rows), "the upsample must have happened"
    # training's device memory (clrf/runtime/devmem.py) holds at least the grid, its links and
    # its optimiser's state, which the checkpoint has
    dm = ev["device_memory"]
    st = checkpoint.load(trained)
    grid = sum(st[k].nbytes for k in ("links", "density", "sh", "opt_density", "opt_sh"))
    assert dm["peak_held_bytes"] >= dm["peak_in_use_bytes"] >= grid
    assert dm["peak_in_use_bytes"] >= dm["in_use_bytes"] > 0


def test_checkpoint_round_trip(device, trained):
    state = checkpoint.load(trained)
    cfg = build_config(overrides=state["run_config"])
    m1 = GridModel.from_state_dict(device, state, cfg.grid)
    o = np.array([[0, 0, 4.0], [0.2, -0.1, 4.0]], np.float32)
    d = np.array([[0, 0, -1.0], [0, 0.1, -1.0]], np.float32)
    r1 = m1.render(o, d)
    s2 = m1.state_dict()
    for k in ("links", "density", "sh", "opt_density", "opt_sh"):
        np.testing.assert_array_equal(s2[k], state[k])
    m2 = GridModel.from_state_dict(device, s2, cfg.grid)
    np.testing.assert_array_equal(m2.render(o, d)["rgb"], r1["rgb"])


@pytest.mark.slow
def test_resume_continues(tmp_path):
    out = tmp_path / "r"
    assert run_cli("train", "--out", out, "--max-seconds", 1.5, *FAST) == 0
    st1 = checkpoint.load(out)
    it1 = st1["iteration"]
    n_rows = len(read_csv(out / "metrics.csv"))
    budget = st1["seconds"] + 1.5   # the first run may overshoot its budget by one step
    assert run_cli("train", "--out", out, "--resume", "--max-seconds", budget) == 0
    st = checkpoint.load(out)
    assert st["iteration"] > it1 and st["seconds"] >= budget
    rows = read_csv(out / "metrics.csv")
    assert len(rows) > n_rows
    assert int(rows[n_rows]["iteration"]) >= it1   # appended, not restarted
    # a second plain train into the same directory is refused
    assert run_cli("train", "--out", out, "--max-seconds", 1) == 2


@pytest.mark.slow
def test_render_and_eval(trained, tmp_path, capsys):
    out = tmp_path / "frames"
    assert run_cli("render", "--ckpt", trained, "--views", "orbit", "--frames", 3, "--out", out) == 0
    pngs = sorted(out.glob("orbit_*.png"))
    assert len(pngs) == 3 and (out / "orbit.gif").is_file()
    import imageio.v3 as iio
    img = iio.imread(pngs[0])
    assert img.shape == (64, 64, 3) and img.std() > 5
    assert run_cli("render", "--ckpt", trained, "--views", "test", "--out", out, "--max-views", 2) == 0
    assert len(list(out.glob("test_*.png"))) == 2
    assert run_cli("eval", "--ckpt", trained, "--out", tmp_path / "ev.json") == 0
    ev = json.loads((tmp_path / "ev.json").read_text())
    assert len(ev["views"]) == 8
    assert "mean over 8 views" in capsys.readouterr().out


@pytest.mark.slow
def test_train_on_tiny_lego(scene, tmp_path):
    out = tmp_path / "tl"
    rc = run_cli("train", "--data", scene("tiny_lego"), "--out", out, "--max-seconds", 6,
                 "--set", "grid.reso=[[32,32,32],[64,64,64]]", "--set", "grid.upsample_at=[15]",
                 "--set", "train.eval_every=3")
    assert rc == 0
    ev = json.loads((out / "eval.json").read_text())
    assert ev["n_views"] == 6 and ev["psnr"] > 17   # grey start is ~14 dB


def test_config_precedence(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"grid": {"batch_size": 1234, "step": 0.7}}))
    cfg = build_config("tiny", str(f), {"grid": {"step": 0.3}})
    assert cfg.grid.batch_size == 1234          # file over preset
    assert cfg.grid.step == 0.3                 # command line over file
    assert cfg.grid.upsample_at == [250]        # preset over defaults
    with pytest.raises(ConfigError, match="grid.batch_size"):
        build_config(overrides={"grid": {"batch_size": "many"}})


def test_the_first_ctrl_c_is_a_flag_read_after_the_step():
    """In the training loop a first SIGINT only sets the trainer's flag (so that it cannot be
    raised, and lost, inside a finalizer: a CI run trained on past one that way); a second
    raises KeyboardInterrupt; a process that ignores SIGINT keeps ignoring it."""
    from types import SimpleNamespace
    from clrf.training.trainer import _hold_sigint
    old = signal.getsignal(signal.SIGINT)
    t = SimpleNamespace(_sigint=False)
    try:
        assert _hold_sigint(t)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert t._sigint
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        assert not _hold_sigint(SimpleNamespace(_sigint=False))
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, old)


@pytest.mark.slow
def test_ctrl_c_keeps_a_loadable_checkpoint(tmp_path):
    out = tmp_path / "r"
    env = dict(os.environ)   # the installed clrf (tests/conftest.py)
    cmd = [sys.executable, "-m", "clrf.cli", "train", "--out", str(out), "--max-seconds", "120",
           "--set", "train.checkpoint_every=0.5", *FAST]
    # SIGINT at its default in the child, whatever this process inherited: a shell starting
    # a job in the background (`cmd &`) ignores SIGINT for it, and Python then never turns
    # Ctrl-C into KeyboardInterrupt (a CI run launched that way trained on past the signal)
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.time()
    while not (out / "ckpt.npz").exists() and time.time() - t0 < 60:
        time.sleep(0.2)
    assert (out / "ckpt.npz").exists(), p.stderr.read1().decode() if p.poll() else "no ckpt"
    time.sleep(1.0)
    p.send_signal(signal.SIGINT)
    try:   # read both pipes while waiting: a child blocked on a full pipe never exits
        _, err = p.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        p.kill()
        _, err = p.communicate()
        pytest.fail("clrf train did not exit 60 s after Ctrl-C; its stderr:\n"
                    + err.decode()[-4000:])
    err = err.decode()
    rc = p.returncode
    assert rc == 130, err
    assert "checkpoint kept" in err
    st = checkpoint.load(out)
    assert st["iteration"] > 0
    assert not list(out.glob("*.tmp*")), "no temporary files left behind"


SMALL = {"grid": FAST,
         "splat": ["--set", "train.eval_every=1.0", "--set", "train.eval_views=2"],
         "hash": ["--set", "hash.batch_rays=256", "--set", "hash.samples=64",
                  "--set", "hash.occ_points=8192", "--set", "hash.occ_warmup=5",
                  "--set", "train.eval_every=1.0", "--set", "train.eval_views=2"],
         "nerf": ["--set", "nerf.width=16", "--set", "nerf.depth=2", "--set", "nerf.color_width=16",
                  "--set", "nerf.n_coarse=8", "--set", "nerf.n_fine=8",
                  "--set", "nerf.batch_rays=256", "--set", "train.eval_every=1.0",
                  "--set", "train.eval_views=2"]}


@pytest.mark.parametrize("model", sorted(SMALL))
@pytest.mark.slow
def test_training_evaluates_no_source_strings(model, tmp_path, monkeypatch):
    """CPython remembers a KeyboardInterrupt that ends the eval or exec of a source string,
    even one caught later, and a process started with `python -m` then dies of SIGINT after
    its code exited 130: the Ctrl-C test above failed so, one run in many, when the signal
    landed in pyopencl's ``cltypes.make_float4`` (an ``eval`` per call, two per Adam step of
    the grid). A second run in one process (its imports and kernels already made) evaluates
    no source string, for every model."""
    import builtins
    args = ["--quiet", "train", "--model", model, "--max-seconds", "120",
            "--set", "train.max_iters=30", *SMALL[model]]
    assert run_cli(*args, "--out", tmp_path / "warm") == 0
    seen = []
    for name in ("eval", "exec"):
        def spy(source, *rest, _real=getattr(builtins, name), _name=name):
            if isinstance(source, (str, bytes)):
                seen.append(f"{_name}({str(source)[:60]!r})")
            return _real(source, *rest)
        monkeypatch.setattr(builtins, name, spy)
    assert run_cli(*args, "--out", tmp_path / "run") == 0
    assert not seen, seen[:5]


@pytest.mark.slow
def test_nerf_through_the_cli(tmp_path, capsys):
    out = tmp_path / "n"
    tiny = SMALL["nerf"]
    assert run_cli("train", "--model", "nerf", "--out", out, "--max-seconds", 3, *tiny) == 0
    rows = read_csv(out / "metrics.csv")
    assert "NeRF 2x16" in rows[-1]["model"]
    assert float(rows[-1]["eval_psnr"]) > float(rows[0]["eval_psnr"])
    it1 = checkpoint.load(out)["iteration"]
    assert run_cli("train", "--out", out, "--resume",
                   "--max-seconds", checkpoint.load(out)["seconds"] + 1.0) == 0
    assert checkpoint.load(out)["iteration"] > it1
    assert run_cli("eval", "--ckpt", out, "--max-views", 2) == 0
    assert run_cli("render", "--ckpt", out, "--views", "orbit", "--frames", 2,
                   "--out", tmp_path / "f") == 0
    assert len(list((tmp_path / "f").glob("orbit_*.png"))) == 2
    rc = run_cli("train", "--model", "nerf", "--out", tmp_path / "bad", "--set", "nerf.widht=3")
    assert rc == 2 and "widht" in capsys.readouterr().err


@pytest.mark.slow
def test_run_ends_naming_the_report_renders_and_next_commands(tmp_path, capsys):
    """The last lines of `clrf train` name the report, the renders and the next commands;
    every file path they name exists, and the renders hold render | ground truth."""
    import re
    import imageio.v3 as iio
    out = tmp_path / "r"
    assert run_cli("train", "--out", out, "--max-seconds", 2, *FAST) == 0
    err = capsys.readouterr().err
    tail = err[err.index("clrf: done:"):]
    assert "clrf: report:" in tail and "clrf: renders:" in tail and "clrf: next:" in tail
    named = [Path(p) for p in re.findall(r"(/\S+?\.(?:png|csv|json))\b", tail)]
    assert {p.name for p in named} >= {"error_vs_time.png", "metrics.csv", "eval.json"}
    for p in named:
        assert p.is_file(), p
    renders = sorted((out / "renders").glob("test_*.png"))
    assert len(renders) == 4 and str(out / "renders") in tail
    img = iio.imread(renders[0])
    assert img.shape == (256, 512, 3)   # 64x64 views x 4: render left, ground truth right
    ds_gt = load_procedural()
    view = int(renders[0].stem.split("_")[1])
    np.testing.assert_allclose(img[::4, 256::4] / 255.0, ds_gt.images[view], atol=0.5 / 255 + 1e-6)
    assert f"clrf render --ckpt {out}" in tail and "clrf train --data FOLDER" in tail


def test_default_first_run_config_is_valid():
    """`clrf train` with no arguments: the procedural preset validates, trains for 60 s on the
    whole box (no sphere bound: the floor's corners lie outside the inscribed sphere) and
    reaches its finest grid early in the budget."""
    cfg = build_config("", None, {}, dataset_preset="procedural")
    assert cfg.train.preset == "procedural" and cfg.train.max_seconds == 60.0
    g = cfg.grid
    assert not g.sphere_bound and len(g.reso) >= 2
    assert len(g.upsample_at) == len(g.reso) - 1 and g.upsample_at[-1] <= 600


def test_next_evaluation_keeps_all_of_them_under_their_share():
    from clrf.training.trainer import EVAL_SHARE, next_eval_at
    assert next_eval_at(5.0, 10.0, 0.2, 0.2, 4) == 15.0    # cheap: every eval_every seconds
    for spent, view in ((0.0, 3.0), (3.0, 30.0), (200.0, 120.0), (2.0, 0.8)):   # stretched
        t = next_eval_at(5.0, 10.0, spent, view, 4)
        assert t >= 15.0 and (spent + view) / (t + spent + view) == pytest.approx(EVAL_SHARE)
    # already within the share at eval_every's point: that point
    assert next_eval_at(100.0, 10.0, 2.0, 2.0, 4) == 110.0


def test_the_untrained_point_renders_a_small_view():
    from clrf.training.trainer import ANCHOR_PIXELS, EVAL_MIN_SIDE, anchor_downscale
    for hw in ((533, 800), (400, 400), (1080, 1920), (64, 64), (3000, 12)):
        f = anchor_downscale(hw)
        small = (hw[0] // f) * (hw[1] // f) <= ANCHOR_PIXELS
        assert small or min(hw) // (f + 1) < EVAL_MIN_SIDE, (hw, f)
        assert f == 1 or (hw[0] // (f - 1)) * (hw[1] // (f - 1)) > ANCHOR_PIXELS   # the least
    assert anchor_downscale((533, 800), 8) == 8      # never finer than the periodic ones


def _slow_views(monkeypatch, per_view):
    """Every view the trainer renders made ``per_view`` seconds slower; returns the list of
    (downscale, views) of each evaluation."""
    import clrf.training.trainer as tr
    render, evaluate, calls = tr.render_view, tr.evaluate, []

    def slow_render(*a, **k):
        time.sleep(per_view)
        return render(*a, **k)

    def counted(model, ds, views, *a, **k):
        ev = evaluate(model, ds, views, *a, **k)
        calls.append((k.get("downscale", 1), len(ev["views"])))
        return ev
    monkeypatch.setattr(tr, "render_view", slow_render)
    monkeypatch.setattr(tr, "evaluate", counted)
    return calls


@pytest.mark.slow
def test_slow_evaluations_are_spaced_out(tmp_path, monkeypatch):
    """Each view made 0.6 s slower, against training's 0.2 s interval: each evaluation is put
    off until the evaluations so far and one more view (its cost predicted from the last
    evaluation's per pixel, before it runs) are at most 15 % of the wall time, and renders
    as many views as fit (here one); the untrained model's point renders one view, and the
    run's last periodic evaluation comes before stopping (no final one here)."""
    out = tmp_path / "r"
    opts = [o if o != "train.eval_every=1.0" else "train.eval_every=0.2" for o in FAST]
    # the programs built first (a cold build is training time, and would make two steps
    # seconds long)
    assert run_cli("--quiet", "train", "--out", tmp_path / "warm", "--max-seconds", 60, *opts,
                   "--set", "train.max_iters=10", "--set", "train.final_eval=false") == 0
    calls = _slow_views(monkeypatch, 0.6)
    assert run_cli("train", "--out", out, "--max-seconds", 13, *opts,
                   "--set", "train.final_eval=false") == 0
    every = read_csv(out / "metrics.csv")
    rows = [r for r in every if r["eval_psnr"]]
    # between them, the training loss keeps the configured 0.2 s rhythm in rows of its own
    loss_only = [r for r in every if not r["eval_psnr"]]
    assert len(loss_only) >= 20 and all(r["train_loss"] and r["rays_per_s"] for r in loss_only)
    # (a step that changes the model, the grid's upsampling, may alone take a second)
    losses = [r for r in every if r["train_loss"]]
    gaps = [float(b["seconds"]) - float(a["seconds"]) for a, b in zip(losses, losses[1:])
            if a["model"] == b["model"]]
    assert len(gaps) >= 20 and max(gaps) < 1.0, [(r["seconds"], r["model"]) for r in losses]
    # 0.6 s at 0 s; the next view fits once 1.2 s is 15 % of the wall time (6.8 s of
    # training), the next at 1.8 s (10.2 s); a second view would end past EVAL_STRETCH_MIN_S;
    # then before stopping (the first render's one-off program loads are not counted, and a
    # loaded machine renders slower: ranges)
    assert [c[1] for c in calls] == [1, 1, 1, 1], calls
    assert [r["eval_views"] for r in rows] == ["1"] * 4
    secs = [float(r["seconds"]) for r in rows]
    assert secs[0] == 0.0 and 5.9 <= secs[1] <= 9.0 and 9.5 <= secs[2] < 13.0, secs
    assert secs[3] >= 13.0, secs


@pytest.mark.slow
def test_an_evaluation_renders_the_views_its_share_allows(tmp_path, monkeypatch):
    """Views 0.35 s slower, four an evaluation (1.4 s: spaced out): an evaluation starts a
    view only where it would end within its share, or EVAL_STRETCH_MIN_S, of the wall time:
    one view at 0 s, two of the four at about 4 s (0.35 s and one more view are 15 % of the
    wall time then), two before stopping."""
    out = tmp_path / "r"
    assert run_cli("--quiet", "train", "--out", tmp_path / "warm", "--max-seconds", 60, *FAST,
                   "--set", "train.max_iters=10", "--set", "train.final_eval=false") == 0
    calls = _slow_views(monkeypatch, 0.35)
    assert run_cli("--quiet", "train", "--out", out, "--max-seconds", 6.5, *FAST,
                   "--set", "train.eval_views=4", "--set", "train.final_eval=false") == 0
    rows = [r for r in read_csv(out / "metrics.csv") if r["eval_psnr"]]
    assert [c[1] for c in calls] == [1, 2, 2], calls
    assert [r["eval_views"] for r in rows] == ["1", "2", "2"]
    secs = [float(r["seconds"]) for r in rows]
    assert 3.0 <= secs[1] <= 5.0 and secs[2] >= 6.5, secs


@pytest.mark.slow
def test_the_untrained_point_is_one_downscaled_view(tmp_path, monkeypatch):
    """The untrained model's point is one view, downscaled where a view has more than
    ANCHOR_PIXELS; the quick periodic evaluations that follow render every periodic view at
    full size, the last before stopping, and the final one every test view."""
    import clrf.training.trainer as tr
    monkeypatch.setattr(tr, "ANCHOR_PIXELS", 20 * 20)        # the 64x64 scene: downscale 4
    calls = _slow_views(monkeypatch, 0.0)
    out = tmp_path / "r"
    assert run_cli("--quiet", "train", "--out", out, "--max-seconds", 3, *FAST) == 0
    rows = [r for r in read_csv(out / "metrics.csv") if r["eval_psnr"]]
    assert calls[0] == (4, 1) and all(c == (1, 2) for c in calls[1:-1]) and calls[-1][1] == 8
    assert rows[0]["eval_views"] == "1" and rows[-1]["eval_views"] == "8"
    assert len(rows) >= 3 and [r["eval_views"] for r in rows[1:-1]] == ["2"] * (len(rows) - 2)
    assert rows[-2]["seconds"] == rows[-1]["seconds"]     # before stopping, then the final


@pytest.mark.slow
def test_program_builds_are_not_training_time(tmp_path, monkeypatch):
    """A first run builds its programs (seconds each, cold): the training clock leaves them out,
    as the evaluations' timing does, so a short budget still trains. Each build made 1 s
    slower here: with the builds counted, the 1.5 s budget would end after the first step."""
    import clrf.runtime.programs as programs
    real = programs.build

    def slow(*a, **k):
        time.sleep(1.0)
        return real(*a, **k)
    monkeypatch.setattr(programs, "build", slow)
    out = tmp_path / "r"
    t0 = time.perf_counter()
    assert run_cli("--quiet", "train", "--out", out, "--max-seconds", 1.5, *FAST,
                   "--set", "train.final_eval=false") == 0
    wall = time.perf_counter() - t0
    st = checkpoint.load(out)
    # with the builds on the clock the run would stop after its first step; off it, a 1.5 s
    # budget trains about 20-30 steps here (20 on a loaded machine), so a few is the bound
    assert st["iteration"] > 5 and st["seconds"] >= 1.5
    assert wall > st["seconds"] + 2.0     # the builds happened, outside the clock
