"""The per-view corrections' list and settings (clrf/corrections/base.py, settings.py), and
checkpoints written before the corrections had a package of their own: their keys (``exposure``,
``exposure_m``, ``exposure_v``, ``exposure_steps``, ..., ``pose``, ``pose_m``, ``pose_v``,
``pose_steps``, ``pose_pivot``), spelled out here as the splat and hash models wrote them, load
into the models' lists, save back unchanged, render and resume. The corrections' kernels and
host maths: tests/test_splat_exposure.py, tests/test_hash_exposure.py, tests/test_splat_pose.py;
the layering and the protocol: tests/test_layers.py."""
import numpy as np
import pytest

from clrf.corrections import RAYS, VIEWS, Corrections, Views, build, from_state
from clrf.interface import StateError
from clrf.outputs import checkpoint


def _splat(device, **splat):
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.training.config import build_config
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={"train": {"model": "splat"},
                                                "splat": {"preset": "tiny", "init_points": 300,
                                                          **splat}})
    return registry.get("splat").create(device, cfg, ds, ds.background), ds


def _old_splat_keys(V, rng, with_newer=True) -> dict:
    """A splat checkpoint's correction entries as the model wrote them before the corrections
    package: a colour transform and an Adam state per image (float32 rows, int64 steps), a
    pose correction per image (float64), and (``with_newer``) the keys added later."""
    rows = np.tile(np.eye(3).reshape(-1).tolist() + [0.0, 0.0, 0.0], (V, 1))
    st = {"exposure": (rows + rng.normal(0, 0.05, rows.shape)).astype(np.float32),
          "exposure_m": rng.normal(0, 1e-3, (V, 12)).astype(np.float32),
          "exposure_v": rng.uniform(0, 1e-6, (V, 12)).astype(np.float32),
          "exposure_steps": rng.integers(0, 5, V).astype(np.int64),
          "pose": rng.normal(0, 1e-3, (V, 6)), "pose_m": rng.normal(0, 1e-4, (V, 6)),
          "pose_v": rng.uniform(0, 1e-8, (V, 6)),
          "pose_steps": rng.integers(0, 5, V).astype(np.int64)}
    if with_newer:
        st.update(exposure_masked=False, exposure_hold_until=0.25,
                  pose_pivot=rng.uniform(1.0, 4.0, V))
    return st


@pytest.mark.parametrize("newer", [True, False], ids=["current", "before-pivots-and-holds"])
def test_an_older_splat_checkpoint_loads_saves_renders_and_resumes(device, tmp_path, newer):
    from clrf.splat.model import SplatModel
    m, ds = _splat(device)
    V = len(ds.images)
    old = _old_splat_keys(V, np.random.default_rng(1), newer)
    state = m.state_dict()
    assert not set(old) & set(state)          # the model has no corrections of its own
    state.update(old)
    state["config"] = dict(state["config"], exposure=True, pose_opt=True)
    checkpoint.save(tmp_path / "ckpt.npz", state)
    back = SplatModel.from_state_dict(device, checkpoint.load(tmp_path / "ckpt.npz"))
    exp, pose = back.corrections.get("exposure"), back.corrections.get("pose")
    np.testing.assert_array_equal(exp.rows(), old["exposure"])
    np.testing.assert_array_equal(exp.steps, old["exposure_steps"])
    np.testing.assert_array_equal(pose.params, old["pose"])
    np.testing.assert_array_equal(pose.pivots, old["pose_pivot"] if newer else np.zeros(V))
    assert exp.hold_until == (0.25 if newer else 0.0) and exp.masked is False
    # saved again: the same keys and values (the newer keys added with their old meaning)
    again = back.state_dict()
    for k, v in old.items():
        np.testing.assert_array_equal(np.asarray(again[k]), np.asarray(v), err_msg=k)
    assert {k for k in again if k.startswith(("exposure", "pose"))} == {
        "exposure", "exposure_m", "exposure_v", "exposure_steps", "exposure_masked",
        "exposure_hold_until", "pose", "pose_m", "pose_v", "pose_steps", "pose_pivot",
        "pose_frame", "pose_frame_scale"}
    np.testing.assert_array_equal(again["pose_frame"], np.zeros(6))   # none taken out yet
    np.testing.assert_array_equal(again["pose_frame_scale"], [0.0])
    # renders, and resumes: the dataset attached keeps the corrections, a step trains them
    out = back.render_image(ds.poses[ds.split["test"][0]], ds.intrinsics, ds.hw, depth=False)
    assert np.all(np.isfinite(out["rgb"]))
    back.attach(ds)
    assert back.corrections.get("exposure") is exp and back.corrections.get("pose") is pose
    back.progress = 0.5     # past the hold
    back.corrections.schedule(back.progress)   # and past the pose corrections' start
    v = back.view_of(0)
    assert np.isfinite(back.train_step(0))
    assert pose.steps[v] == old["pose_steps"][v] + 1
    assert exp.steps[v] == old["exposure_steps"][v] + 1


def test_an_older_hash_checkpoint_loads_saves_and_resumes(device, tmp_path):
    from clrf import registry
    from clrf.data import load_dataset
    from clrf.hash.model import HashModel
    from clrf.training.config import build_config
    from clrf.training.trainer import train_on_batch, training_rays
    ds = load_dataset(None)
    cfg = build_config("procedural", overrides={
        "train": {"model": "hash"}, "hash": {"batch_samples": 0, "batch_rays": 256}})
    m = registry.get("hash").create(device, cfg, ds, ds.background)
    assert not m.corrections and not m.ray_index
    V, rng = len(ds.split["train"]), np.random.default_rng(2)
    rows = np.tile(np.eye(3).reshape(-1).tolist() + [0.0, 0.0, 0.0], (V, 1))
    old = {"exposure": (rows + rng.normal(0, 0.05, rows.shape)).astype(np.float32),
           "exposure_m": rng.normal(0, 1e-3, (V, 12)).astype(np.float32),
           "exposure_v": rng.uniform(0, 1e-6, (V, 12)).astype(np.float32),
           "exposure_steps": np.array([7], np.int64),
           "exposure_pixels": int(ds.hw[0] * ds.hw[1]), "exposure_masked": False}
    state = dict(m.state_dict(), **old)
    state["config"] = dict(state["config"], exposure=True)
    checkpoint.save(tmp_path / "ckpt.npz", state)
    back = HashModel.from_state_dict(device, checkpoint.load(tmp_path / "ckpt.npz"))
    exp = back.corrections.get("exposure")
    assert back.ray_index and exp.steps == 7 and exp.pixels == old["exposure_pixels"]
    np.testing.assert_array_equal(exp.rows(), old["exposure"])
    again = back.state_dict()
    for k, v in old.items():
        np.testing.assert_array_equal(np.asarray(again[k]), np.asarray(v), err_msg=k)
    assert np.isfinite(train_on_batch(back, training_rays(device, ds), 0, 0, back.batch_size))
    assert exp.steps == 8 and not np.array_equal(exp.rows(), old["exposure"])


@pytest.mark.parametrize("missing", ["exposure_m", "pose_steps"])
def test_an_unreadable_correction_is_a_state_error(device, missing):
    from clrf.splat.config import SplatConfig
    st = _old_splat_keys(4, np.random.default_rng(3))
    del st[missing]
    what = "exposure transforms" if missing.startswith("exposure") else "pose corrections"
    with pytest.raises(StateError, match=what):
        from_state(device, SplatConfig(), st, Views(scale=2.0), VIEWS)


class _Fake:
    def __init__(self, name, changes, batches="views", n_images=3):
        self.name, self.changes, self.batches, self.n_images = name, changes, batches, n_images


def test_an_empty_list_passes_everything_through():
    corr = Corrections()
    cam, rgb, grad = object(), object(), object()
    assert corr.camera(cam, 1) is cam and corr.apply(rgb, 1) is rgb
    assert corr.background(1, (1.0, 0.5, 0.0)) == (1.0, 0.5, 0.0)
    assert corr.colour_backward(1, rgb, None, None, grad, 0.5, None, None) is grad
    assert not corr and corr.colour is None and not corr.moves_cameras and not corr.ray_index
    assert corr.state_dict() == {} and corr.summaries() == {} and corr.describe() == ""
    assert corr.get("exposure") is None


def test_the_list_takes_one_of_each_change():
    with pytest.raises(ValueError, match="at most one"):
        Corrections([_Fake("a", "colour"), _Fake("b", "colour")])
    with pytest.raises(ValueError, match="one of each name"):
        Corrections([_Fake("a", "colour"), _Fake("a", "camera")])
    with pytest.raises(ValueError, match="is not one of"):
        Corrections([_Fake("a", "depth")])
    both = Corrections([_Fake("a", "colour", "rays"), _Fake("b", "camera")])
    assert both.colour.name == "a" and both.moves_cameras and both.ray_index


def test_build_reads_the_sections_keys_and_keeps_a_checkpoints_corrections(device):
    """splat.exposure / splat.pose_opt / hash.exposure turn them on with their sections'
    rates, pulls, matrix, clip and fit; a checkpoint's correction is kept where it has a row
    per image, replaced where it has not, and kept when its setting is off."""
    from clrf.hash.config import HashConfig
    from clrf.splat.config import SplatConfig
    sc = SplatConfig(exposure=True, pose_opt=True, lr_exposure=0.02, lr_exposure_final=0.002,
                     exposure_matrix="diagonal", exposure_fit=0.5, exposure_fit_after=0.2,
                     exposure_clip=True, exposure_clip_inward=True, lr_pose=0.004,
                     pose_reg=0.3)
    corr = build(device, sc, Views(3, masked=True, scale=2.0, pivots=lambda: [1.0, 2.0, 3.0]),
                 VIEWS)
    exp, pose = corr.get("exposure"), corr.get("pose")
    assert [c.name for c in corr] == ["exposure", "pose"]
    assert (exp.lr, exp.lr_final, exp.matrix, exp.clip, exp.masked, exp.fit_eta,
            exp.fit_after) == (0.02, 0.002, 1, 2, True, 0.5, 0.2)
    assert (pose.lr, pose.lr_final, pose.reg, pose.scale) == (0.004, sc.lr_pose_final, 0.3, 2.0)
    np.testing.assert_array_equal(pose.pivots, [1.0, 2.0, 3.0])
    corr.schedule(1.0)
    assert exp.lr == pytest.approx(0.002) and pose.lr == pytest.approx(sc.lr_pose_final)
    again = build(device, sc, Views(3, masked=False, scale=2.0, pivots=lambda: [0, 0, 0]),
                  VIEWS, corr)
    assert again.get("exposure") is exp and again.get("pose") is pose and not exp.masked
    assert build(device, SplatConfig(), Views(3), VIEWS, corr).get("pose") is pose
    fewer = build(device, sc, Views(2, pivots=lambda: [0, 0]), VIEWS, corr)
    assert fewer.get("exposure").n_images == 2 and fewer.get("pose").n_images == 2
    hc = HashConfig(exposure=True, beta2=0.95, exposure_reg=0.01)
    ray = build(device, hc, Views(3, pixels=16), RAYS).colour
    assert (ray.batches, ray.pixels, ray.reg, ray.opt.beta2) == ("rays", 16, 0.01, 0.95)
    assert not build(device, HashConfig(), Views(3, pixels=16), RAYS)
