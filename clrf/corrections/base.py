"""The per-view correction protocol and the list a model holds (clrf/corrections/__init__.py
has the overview).

A correction learns a few numbers per training image that the scene cannot explain: what it
changes is the camera (``changes`` "camera": the pose a view is rendered from) or the colour
(``changes`` "colour": what the loss sees of a render). ``batches`` says which models can hold
it, as Kind.batches does: "views" for models that train on whole views (each step one image
v), "rays" for models whose batches mix rays of many images (each ray's image from its index
in the concatenated training images).

Every correction has the members of ``Correction``; the hooks its model calls are those of the
protocol of its (changes, batches), ``PROTOCOLS``. A model holds a ``Corrections`` and calls
the list's hooks, never one correction by its name; the trainer and the command line find one
by name (``get``) where they report it.

>>> corr = Corrections([exposure, pose])
>>> cam = corr.camera(cam, v)                        # the corrected camera of view v
>>> bg = corr.background(v, bg)                      # the background to render view v on
>>> shown = corr.apply(rgb, v, T, bg)                # what the loss sees
>>> grad = corr.colour_backward(v, rgb, T, bg, grad_shown, progress, images, background)
>>> corr.camera_step(v, cam.viewmat, dR, dt)         # from the renderer's camera gradient
>>> o, d = corr.ray_camera.rays(index, o0, d0)       # ray batches: the corrected cameras' rays
>>> corr.ray_camera.step_rays(index, d, ray_grad)    # from each ray's dL/d(origin, direction)
"""
from __future__ import annotations

from typing import Optional, Protocol, runtime_checkable

CAMERA, COLOUR = "camera", "colour"       # Correction.changes
VIEWS, RAYS = "views", "rays"             # Correction.batches (as Kind.batches)
RAY_STATE = 8   # floats per ray of the composite state a RayColourCorrection reads (colour c,
#                 opacity a, then unread entries: cl/splat_exposure.cl's stride)


@runtime_checkable
class Correction(Protocol):
    """What every per-view correction has.

    name        its checkpoint keys' prefix (``exposure``, ``exposure_m``, ...; ``pose``,
                ``pose_m``, ...) and its name in ``Corrections.get``
    changes     CAMERA or COLOUR
    batches     VIEWS or RAYS: the models that can hold it
    n_images    its rows: one per image
    """
    name: str
    changes: str
    batches: str
    n_images: int

    def schedule(self, progress: float) -> None:
        """Its learning rate at the budget fraction ``progress`` (the model's budget hook)."""

    def after_pass(self) -> None:
        """After each pass of a model over its training views: the rows' common part taken
        out (recentring), where it has one."""

    def state_dict(self) -> dict:
        """Its checkpoint entries (numpy arrays and Python scalars), keys prefixed by name."""

    def summary(self) -> dict:
        """What eval.json records of it under ``<name>_correction`` (with ``images``: how many
        images it corrected); empty where it records nothing."""

    def report(self, summary: dict) -> str:
        """The sentence ``clrf eval`` prints of ``summary`` (empty where it prints none)."""

    def describe(self) -> str:
        """A few words for progress lines."""


@runtime_checkable
class CameraCorrection(Correction, Protocol):
    """A correction of the camera a training view is rendered from (the renderer gives the
    gradient of the loss in the corrected camera's world-to-camera [R t])."""

    def camera(self, cam, v: int):
        """``cam`` (a camera record with a world-to-camera ``viewmat`` [4, 4]) as view v is
        rendered: the same record with the corrected viewmat."""

    def step(self, v: int, viewmat, dR, dt) -> None:
        """One optimiser step of view v's correction from dL/dR [3, 3], dL/dt [3] of its
        corrected camera ``viewmat``."""


@runtime_checkable
class ViewColourCorrection(Correction, Protocol):
    """A correction of the colours of whole views (the loss sees ``apply`` of the render)."""

    def background(self, v: int, background) -> tuple:
        """The background colour to render view v on, given the scene's ``background``."""

    def apply(self, rgb, v: int, T=None, background=None):
        """What the loss sees of view v's render ``rgb`` [H, W, 3] (a new device array); ``T``
        [H, W] its transmittance and ``background`` the colour it was rendered on (what a
        correction that keeps a masked capture's background needs)."""

    def backward_and_step(self, rgb, T, background, grad_out, v: int):
        """dL/drgb (a new device array) from dL/dout of the render ``rgb`` and its
        transmittance ``T`` on ``background``, and one optimiser step of view v's row."""

    def train_view(self, v: int, rgb, T, background, grad_out, progress: float, images,
                   scene_background):
        """dL/drgb as ``backward_and_step`` gives it, the row trained as the correction's
        settings say at the budget fraction ``progress`` (an optimiser step, a fit to
        ``images[v]`` on ``scene_background``, or none while it is held)."""


@runtime_checkable
class RayColourCorrection(Correction, Protocol):
    """A correction of the colours of ray batches (ray i from image ``index[i] // pixels``),
    around a volume renderer's composite state (its backward then runs unchanged)."""

    def forward(self, state, background, target, index):
        """(the target to give the renderer's backward [n, 3], each ray's squared residual
        [n]) of the rays' composite ``state`` on ``background``."""

    def in_backward(self, index):
        """Its inputs for a renderer that applies it inside its own backward, on whole
        pixels (the grid, cl/grid_render.cl RAY_EXPOSURE): a record of what the kernel reads
        and the state and residuals it writes in place of ``forward``'s."""

    def add_background(self, pk, sigma, loss_scale: float, dsigma) -> None:
        """Adds the background's share of dL/dsigma to ``dsigma`` (the backward ran on
        black); ``pk`` the rays' samples: n, m, offsets [n + 1] and segment lengths dt [m]
        (the hash marcher's Packed, NeRF's composite_state)."""

    def backward(self, state, background, index, loss_scale: float) -> None:
        """The rows' gradient over the last ``forward``'s rays, kept for the next
        ``backward_and_step`` (a renderer whose loss has several passes over the batch, each
        with its own ``forward``: NeRF's coarse pass)."""

    def backward_and_step(self, state, background, index, loss_scale: float) -> None:
        """The rows' gradient over the last ``forward``'s rays (plus what ``backward`` kept)
        and one optimiser step."""


@runtime_checkable
class RayCameraCorrection(Correction, Protocol):
    """A correction of the cameras that made ray batches (ray i from image ``index[i] //
    pixels``): the batch's rays are remade from the corrected cameras, and the model's
    dL/d(origin, direction) of each ray trains them."""

    def rays(self, index, origins, dirs):
        """(origins, dirs) [n, 3] (new device arrays) of the batch's rays as their images'
        corrected cameras make them, from those the given cameras made."""

    def gradient_due(self) -> bool:
        """Whether this training step forms the cameras' gradient and calls ``step_rays``
        (one step in ``pose_opt_every``); counts the step. The other steps use ``rays``
        alone."""

    def step_rays(self, index, dirs, ray_grad) -> None:
        """One optimiser step of each image with rays in the batch, from the rays' corrected
        directions ``dirs`` [n, 3] and dL/d(origin, direction) ``ray_grad`` [n, 6]."""

    @property
    def trains(self) -> bool:
        """Whether the next batch takes a step: False while the correction waits for its start
        (its cameras are then the given ones, so the model renders the stored rays and
        computes no camera gradient: that gradient costs a fifth of a hash step)."""


# the hooks a correction of (changes, batches) has (tests/test_layers.py checks each class)
PROTOCOLS = {(CAMERA, VIEWS): CameraCorrection, (COLOUR, VIEWS): ViewColourCorrection,
             (COLOUR, RAYS): RayColourCorrection, (CAMERA, RAYS): RayCameraCorrection}


class Corrections:
    """The corrections a model holds, in order; at most one of each kind of change. Empty:
    every hook passes its input through.

    >>> corr = Corrections()          # a model without corrections
    >>> corr.camera(cam, 3) is cam, corr.apply(rgb, 3) is rgb, bool(corr)
    (True, True, False)
    """

    def __init__(self, items=()):
        self.items = tuple(items)
        for c in self.items:
            if (c.changes, c.batches) not in PROTOCOLS:
                raise ValueError(f"correction {c.name!r}: changes {c.changes!r} of "
                                 f"{c.batches!r} is not one of {sorted(PROTOCOLS)}")
        names = [c.name for c in self.items]
        if len(set(names)) != len(names):
            raise ValueError(f"corrections: one of each name, got {names}")
        for what in (CAMERA, COLOUR):
            if sum(c.changes == what for c in self.items) > 1:
                raise ValueError(f"corrections: at most one that changes the {what}, got "
                                 f"{names}")

    def __iter__(self):
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def get(self, name: str):
        """The correction called ``name``, or None."""
        for c in self.items:
            if c.name == name:
                return c
        return None

    def _changing(self, what: str):
        for c in self.items:
            if c.changes == what:
                return c
        return None

    @property
    def colour(self):
        """The colour correction (ViewColourCorrection or RayColourCorrection), or None."""
        return self._changing(COLOUR)

    @property
    def ray_camera(self):
        """The camera correction of ray batches (RayCameraCorrection) while it trains, or None
        (none, or one still waiting for its start: ``RayCameraCorrection.trains``)."""
        c = self._changing(CAMERA)
        return c if c is not None and c.batches == RAYS and c.trains else None

    @property
    def moves_cameras(self) -> bool:
        """Whether a correction changes the cameras (the renderer then computes the camera's
        gradient for ``camera_step``)."""
        return self._changing(CAMERA) is not None

    @property
    def ray_index(self) -> bool:
        """Whether training batches must carry each ray's index in the training images."""
        return any(c.batches == RAYS for c in self.items)

    # ---- the hooks of a model that trains on views ------------------------------------------
    def camera(self, cam, v: int):
        """View v's camera as it is rendered (``cam`` itself without a camera correction)."""
        c = self._changing(CAMERA)
        return cam if c is None else c.camera(cam, v)

    def camera_step(self, v: int, viewmat, dR, dt) -> None:
        c = self._changing(CAMERA)
        if c is not None:
            c.step(v, viewmat, dR, dt)

    def background(self, v: int, background) -> tuple:
        """The background to render view v on (``background`` without a colour correction)."""
        c = self._changing(COLOUR)
        return background if c is None else c.background(v, background)

    def apply(self, rgb, v: int, T=None, background=None):
        """What the loss sees of view v's render (``rgb`` itself without a colour
        correction), rendered with transmittance ``T`` on ``background``."""
        c = self._changing(COLOUR)
        return rgb if c is None else c.apply(rgb, v, T, background)

    def colour_backward(self, v: int, rgb, T, background, grad_out, progress: float, images,
                        scene_background):
        """dL/drgb from dL/d(what the loss saw) (``grad_out`` itself without a colour
        correction), the colour correction trained (ViewColourCorrection.train_view)."""
        c = self._changing(COLOUR)
        if c is None:
            return grad_out
        return c.train_view(v, rgb, T, background, grad_out, progress, images,
                            scene_background)

    # ---- every model ---------------------------------------------------------------------
    def schedule(self, progress: float) -> None:
        for c in self.items:
            c.schedule(progress)

    def after_pass(self) -> None:
        for c in self.items:
            c.after_pass()

    def state_dict(self) -> dict:
        out = {}
        for c in self.items:
            out.update(c.state_dict())
        return out

    def summaries(self) -> dict:
        """{"<name>_correction": summary} of those that record one (eval.json)."""
        out = {}
        for c in self.items:
            s = c.summary()
            if s:
                out[f"{c.name}_correction"] = s
        return out

    def describe(self) -> str:
        """Their progress words, joined ("" without corrections)."""
        return ", ".join(c.describe() for c in self.items)


NONE = Corrections()   # what a model without a ``corrections`` attribute holds (``of``)


def of(model) -> Corrections:
    """The corrections ``model`` holds (an empty list for a kind without any)."""
    found: Optional[Corrections] = getattr(model, "corrections", None)
    return NONE if found is None else found
