"""The model interface: what a trainable representation offers, and how it declares itself.

A representation (the Plenoxels grid, NeRF, the hash grid, ...) is a package of its own. It
implements :class:`Model` and describes itself with one :class:`Kind` (its ``kind.py``), which
the registry (clrf/registry.py) lists. Training, outputs, the viewer and the command line talk
to these two only: adding a representation adds a package and one line in the registry.

The budget hook takes a :class:`Budget` (how much of the run is spent, and the training rays
for the representations that look at them between steps), never the trainer itself.

Example (what the trainer does with a kind, shapes as numpy arrays)::

    kind = registry.get("grid")
    model = kind.create(device, cfg, ds, background)           # a Model
    msg = model.on_iteration(it, Budget(it, seconds, fraction, rays))
    loss = model.train_step(it, origins[B, 3], dirs[B, 3], rgb[B, 3])
    out = model.render(origins[N, 3], dirs[N, 3])              # rgb [N, 3], depth [N], acc [N]
    sigma, rgb = model.export_fields(points_dev[n, 3], dirs_dev[n, 3] or None)   # on the device
    kind.from_state(device, model.state_dict(), cfg)            # the same model back
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional, Protocol, runtime_checkable

import numpy as np


class StateError(ValueError):
    """A checkpoint's state does not fit the model asked for (a wrong brick, a wrong shape):
    the caller reports it as a bad checkpoint."""


class Unsupported(ValueError):
    """What a model kind cannot do (a camera model, an export, single rays): the CLI reports it
    as bad input, naming what the kind offers instead."""


class InputFileError(ValueError):
    """A file a model kind reads itself (a splat PLY to start from) is unusable: the message
    names the file, what is wrong and the fix; the CLI reports it as bad input."""


@dataclass
class Budget:
    """The run's clock at the start of a step, as the budget hook sees it."""
    iteration: int          # the step about to run
    seconds: float          # training seconds so far (evaluation excluded)
    fraction: float         # the budget spent: max(seconds / max_seconds, it / max_iters), <= 1
    rays: Any = None        # the training ray store (strided(k) -> origins, dirs), for pruning


@runtime_checkable
class Model(Protocol):
    """A trainable representation on one device.

    kind            the registry name (``--model``, the config section, the checkpoint's
                    "kind")
    device          the clrf Device it lives on
    batch_size      rays of the next training step (a model may adapt it step by step)
    view_dependent  colours depend on the view direction (export then looks along normals)
    sample_length   the renderer's own step length h in model units (export's default level
                    is ln 2 / h: one step absorbs half the light)
    """
    kind: str
    device: Any

    @property
    def batch_size(self) -> int: ...

    def train_step(self, it: int, origins, dirs, target, background=None) -> float:
        """One optimiser step on a batch (device arrays [B, 3]); returns the batch's loss
        (mean squared error) as a float, or a device scalar the caller reads when it logs."""

    def on_iteration(self, it: int, budget: Budget) -> Optional[str]:
        """The budget hook, before step ``it``: schedules, pruning, upsampling. Returns a log
        line or None."""

    def render(self, origins, dirs) -> dict:
        """numpy float32 rays [N, 3] -> dict of numpy: rgb [N, 3], depth [N], acc [N]."""

    def export_fields(self, points, dirs):
        """Density sigma [n] and colour rgb [n, 3] (device arrays) at device points [n, 3],
        looking along ``dirs`` [n, 3] (None: the model's choice)."""

    def export_block(self, block: int) -> int:
        """How many points one export_fields call may take (its scratch stays bounded)."""

    def native_reso(self, bbox) -> Optional[tuple]:
        """A mesh resolution of the model's own over ``bbox`` [2, 3], or None."""

    def state_dict(self) -> dict: ...

    # Optional, for models that render whole cameras rather than rays (Kind.batches "views"):
    #   render_image(c2w [4, 4], intrinsics (fx, fy, cx, cy), hw (H, W), depth=True) -> dict
    #   of numpy rgb [H, W, 3], acc [H, W] and, where asked, depth [H, W] (OpenGL camera
    #   axes: x right, y up, -z ahead)
    # Evaluation, `clrf render` and the viewer use it where a model has it (render_view).
    #   attach(ds, max_images): the training views of dataset ds (the first max_images; 0:
    #   all); the trainer calls it after create and after from_state (a resumed run).
    # Optional, for models with per-view corrections (a colour transform per image, a pose
    # correction per camera: clrf/corrections): ``corrections``, the list it holds and calls;
    # the trainer and `clrf eval` report them (clrf.corrections.of(model)).
    # Optional, for `clrf eval --refine-poses N` (BARF's protocol): refine_view_pose(c2w,
    #   intrinsics, hw, image [H, W, 3], steps, lr, rays=None) -> (the corrected c2w [4, 4],
    #   the correction's summary), the model held still; ``rays``: a callable returning the
    #   camera's (origins, dirs) [H W, 3] (the ray models refine on them: splat ignores it).
    # What a kind cannot do raises Unsupported.

    def describe(self) -> str:
        """One line for the log: size, stage, what changed."""


@dataclass(frozen=True)
class Export:
    """A file (or folder) only this kind can write: ``clrf export --NAME PATH``.
    ``write(model, path, state, views)`` writes it (atomically, in the format its ending names)
    and returns a one-line summary (``state``: the checkpoint's; ``views``: an ExportViews
    where ``wants_views``, else None); ``suffix`` is the file ending it requires (e.g. ".ply"),
    or a tuple of the endings it accepts, the usual one first (e.g. (".ply", ".spz",
    ".splat")), and "/" for a folder. ``check(path)``, where given, runs before the checkpoint
    loads (what the export needs is installed, the path can be written) and raises a
    ValueError naming the fix otherwise (Unsupported)."""
    help: str
    suffix: str | tuple
    write: Callable
    check: Optional[Callable] = None
    wants_views: bool = False

    @property
    def folder(self) -> bool:
        """Whether the export writes a folder (``suffix`` "/")."""
        return self.suffixes == ("/",)

    @property
    def suffixes(self) -> tuple:
        """The endings accepted, lower case, the usual one first."""
        return (self.suffix,) if isinstance(self.suffix, str) else tuple(self.suffix)

    def suffix_list(self) -> str:
        """'.ply', or '.ply, .spz or .splat' (every ending), for messages."""
        s = self.suffixes
        return s[0] if len(s) == 1 else ", ".join(s[:-1]) + " or " + s[-1]


@dataclass(frozen=True)
class ExportViews:
    """The cameras an export that opens at a view gets from the command line: the run's
    dataset (or ``--data``'s) or None with ``why`` there is none, and ``orbit(n, radius,
    elevation_deg, center)``: camera-to-world poses [n, 4, 4] of ``clrf render``'s orbit."""
    dataset: Any
    why: str
    orbit: Callable


@dataclass(frozen=True)
class Kind:
    """One representation as the registry lists it.

    name           ``--model NAME``, its configuration section ``NAME.*`` and its checkpoints'
                   "kind"
    title          one line for ``--help``
    config         the section's dataclass; ``checks()`` returns (ok, "NAME.field", message)
                   triples; with ``presets``, ``from_preset(name)`` builds one
    presets        the section's own presets (``--set NAME.preset=P`` replaces the section)
    scene_presets  {scene preset name: this section's overrides} (clrf/training/config.py
                   names the scene presets; a dataset picks one)
    create         (device, cfg, ds, background) -> Model: a new model for dataset ``ds``
    from_state     (device, state, cfg) -> Model: a checkpoint's model back
    memory         (cfg, n_rays, caps, tuning, is_cpu) -> (stages, fix): the run's phases
                   (clrf.runtime.memory.StageEstimate list) and what to lower when it does not
                   fit
    workload       a clrf.runtime.workload.Workload: the timed run that picks this kind's
                   default device (None: the probe's choice)
    selfcheck      a clrf.runtime.selfcheck.GradientCheck the device must pass before this
                   kind trains on it (None: none)
    distributed    (comm) -> a factory with check(cfg), rank_config(cfg) and the create /
                   from_state / brick of a multi-process run (None: one process only)
    check          (cfg, ds, caps) -> None: checks a new run's inputs (dataset, files the
                   configuration names) on the chosen device's capabilities before anything
                   is planned or written; raises a bad-input error (None: nothing to check)
    exports        {flag name: Export}: files of this kind's own for ``clrf export``
    batches        "rays": train_step gets a batch of rays drawn from every training pixel;
                   "views": the model draws its own training views (it got the dataset at
                   create) and train_step gets None for origins, dirs and target
    world_cameras  True: the kind needs world-space cameras, so a forward-facing capture (NDC
                   rays for the others) comes to it as its world-space view
                   (clrf/data/world.py), in training and in evaluation alike
    wants_points   (cfg) -> bool: a new run of this configuration starts from the scene's
                   sparse points, so train.points "auto" triangulates a photographed capture
                   that has none where pycolmap is installed (clrf/data/triangulate.py);
                   None: never
    programs       (device, cfg) -> None: asks ``device.program`` for every program a run of
                   ``cfg`` builds (training, rendering, the workload and self-check), through
                   the same functions the model calls; on a recording stand-in
                   (clrf/training/catalog.py) this lists them for offline builds
                   (tools/gpu_builds.py). None: none listed
    scene_file     (path) -> a checkpoint's state, or None: a file of this kind's own that
                   commands taking a trained scene (``--ckpt``) read as one, such as a splat
                   file another tool wrote; a file it cannot read raises ValueError naming it.
                   None: checkpoints only
    """
    name: str
    title: str
    config: type
    create: Callable
    from_state: Callable
    memory: Callable
    presets: Mapping = field(default_factory=dict)
    scene_presets: Mapping = field(default_factory=dict)
    workload: Any = None
    selfcheck: Any = None
    distributed: Optional[Callable] = None
    exports: Mapping = field(default_factory=dict)
    batches: str = "rays"
    check: Optional[Callable] = None
    world_cameras: bool = False
    wants_points: Optional[Callable] = None
    programs: Optional[Callable] = None
    scene_file: Optional[Callable] = None


def render_view(model, c2w, intrinsics, hw, rays, depth: bool = True):
    """rgb [H, W, 3], depth [H, W], acc [H, W] of one camera: the model's render_image where it
    has one (its depth only where ``depth`` asks for it), else its render of ``rays()`` (a
    callable returning origins, dirs [H*W, 3])."""
    H, W = int(hw[0]), int(hw[1])
    if hasattr(model, "render_image"):
        return model.render_image(c2w, intrinsics, (H, W), depth=depth)
    o, d = rays()
    # every output the model gives, as an image (rgb [H, W, 3], depth and acc [H, W])
    return {k: np.asarray(v).reshape(H, W, *np.shape(v)[1:])
            for k, v in model.render(o, d).items()}
