"""``clrf export --web DIR``: a folder that shows a splat scene in a browser served by any static
file server (``python -m http.server``), drawn by viser's web client (the extra 'web': viser,
its version pinned in setup.cfg; nothing of the page is clrf's own renderer).

  DIR/index.html   viser's built client, the one self-contained HTML file its wheel ships
                   (about 0.8 MB), with one line added to its head: when the address names no
                   recording (``?playbackPath=...``) it names SCENE_FILE
  DIR/scene.viser  viser's recording of the scene (``server.get_scene_serializer()``: zstd of
                   msgpack and raw buffers): the Gaussians, the scene's up direction, the
                   opening camera and the background

What viser keeps of a Gaussian (32 bytes before compression): the centre (float32), the
covariance R S S R^T (its six upper terms, float16) and an RGBA colour (uint8): SH degree 0,
0.5 + SH_C0 dc clipped to 0..1, and the opacity sigmoid(logit). View-dependent colour (SH
degree >= 1) is dropped. An anti-aliased model's 3D filter is baked in first, as for
``--splats`` (model.viewer_params).

The opening camera is the first test view of the run's dataset (the first training view where
there is no test split): its position, viewing axis, up axis and vertical field of view, the
look-at point on the viewing axis level with the Gaussians' median centre (where the orbit
controls turn about), the scene's up direction the training cameras' mean up axis. A splat file
given as the checkpoint has no cameras (unless ``--data`` names a capture), nor has a run whose
dataset cannot be loaded: the page then opens where ``clrf render``'s orbit starts (world z up,
30 degrees above the box's centre, 1.15 box diagonals away).

>>> write_web(model, state, Path("site"))          # doctest: +SKIP
'saved site/ (viser 1.1.1): ...'
"""
from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path

import numpy as np

from ..interface import Unsupported
from ..runtime.atomicfile import atomic_dir

SCENE_FILE = "scene.viser"
PAGE_FILE = "index.html"
SETUP = "bash tools/setup.sh web"
SH_C0 = 0.28209479177387814          # the degree-0 SH basis constant
ORBIT_ELEVATION_DEG = 30.0           # the opening view without cameras: clrf render's orbit
ORBIT_DIAGONALS = 1.15               # its distance from the box centre, in box diagonals
CLIP_RANGE = 1e3                     # near and far planes at look-at distance / and * this
BACKGROUND_SIDE = 8                  # pixels of the uniform background image's side
# the line the page's head gets: a recording named unless the address names one (other
# parameters, such as viser's ?logCamera, are kept)
PLAYBACK_SCRIPT = ("<script>(function(){{var q=new URLSearchParams(location.search);"
                   "if(!q.has('playbackPath')){{q.set('playbackPath','{scene}');"
                   "history.replaceState(null,'','?'+q.toString()+location.hash);}}}})();"
                   "</script>")


class WebExportError(Unsupported):
    """Bad input to ``--web``: the CLI reports it as ``clrf: error: ...`` (exit 2)."""


def need_viser():
    """The viser module; a WebExportError naming the extra where it is missing."""
    try:
        import viser
    except ImportError:
        raise WebExportError(f"--web needs viser's web client, the extra 'web': run `{SETUP}` "
                             f"(or pip install 'clrf[web]')") from None
    return viser


def check_web_dir(path) -> Path:
    """``path`` as the folder to write: a new or empty folder, else WebExportError."""
    p = Path(path)
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise WebExportError(f"--web {path}: exists and is not a folder: pass a new folder")
        if any(p.iterdir()):
            raise WebExportError(f"--web {path}: the folder exists and is not empty: pass a new "
                                 f"or empty folder (nothing is overwritten)")
    return p


# ---- what viser draws ----------------------------------------------------------------------------
def covariances(log_scales, quats) -> np.ndarray:
    """R S S R^T of each Gaussian, float64 [n, 3, 3], from log scales [n, 3] and quaternions
    [n, 4] (w, x, y, z; any norm). One Gaussian with scales (2, 1, 1) turned 90 degrees about
    z: diag(1, 4, 1)."""
    q = np.asarray(quats, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-30)
    w, x, y, z = q.T
    r = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                 -1).reshape(-1, 3, 3)
    m = r * np.exp(np.asarray(log_scales, np.float64))[:, None, :]
    return m @ m.transpose(0, 2, 1)


def colours(sh, opacity_logits) -> tuple:
    """(RGB [n, 3] of SH degree 0 clipped to 0..1, opacity [n, 1]), float64."""
    rgb = np.clip(0.5 + SH_C0 * np.asarray(sh, np.float64)[:, 0, :], 0.0, 1.0)
    o = 0.5 * (1.0 + np.tanh(0.5 * np.asarray(opacity_logits, np.float64)))
    return rgb, o.reshape(-1, 1)


# ---- the opening camera ----------------------------------------------------------------------
def opening_camera(state, means, views) -> dict:
    """The camera the page opens at (module doc): position, look_at, up (camera), scene_up,
    fov (vertical, radians), near, far and what it is (``what``), world units."""
    means = np.asarray(means, np.float64).reshape(-1, 3)
    centre = np.median(means, 0) if len(means) else np.zeros(3)
    ds, why = views.dataset, views.why
    if ds is not None:
        test = np.asarray(ds.split.get("test", []))
        split = "test" if len(test) else "train"
        view = int((test if len(test) else np.asarray(ds.split["train"]))[0])
        pose = np.asarray(ds.poses[view], np.float64)
        fy, height = float(ds.intrinsics[1]), ds.hw[0]
        scene_up = np.asarray(ds.poses, np.float64)[np.asarray(ds.split["train"]), :3, 1].sum(0)
        what = f"{split} view {view} of {ds.name}"
    else:
        meta = state["dataset"]
        bbox = np.asarray(meta["bbox"], np.float64).reshape(2, 3)
        radius = ORBIT_DIAGONALS * float(np.linalg.norm(bbox[1] - bbox[0]))
        pose = views.orbit(1, radius, ORBIT_ELEVATION_DEG, bbox.mean(0))[0]
        centre = bbox.mean(0)
        fy, height = float(meta["intrinsics"][1]), int(meta["H"])
        scene_up = np.array([0.0, 0.0, 1.0])
        what = f"a view of the scene's box ({why})"
    position, forward = pose[:3, 3], -pose[:3, 2]
    forward = forward / np.linalg.norm(forward)
    to_centre = centre - position
    depth = float(to_centre @ forward)
    if not depth > 1e-6 * max(float(np.linalg.norm(to_centre)), 1e-30):
        depth = max(float(np.linalg.norm(to_centre)), 1e-3)   # the centre is behind the camera
    return {"position": position, "look_at": position + depth * forward, "up": pose[:3, 1],
            "scene_up": scene_up / np.linalg.norm(scene_up),
            "fov": 2.0 * math.atan(0.5 * height / fy),
            "near": depth / CLIP_RANGE, "far": depth * CLIP_RANGE, "what": what}


# ---- the folder ----------------------------------------------------------------------------
def recording(viser, params, camera, background) -> bytes:
    """viser's recording (.viser bytes) of the Gaussians ``params`` (means, log_scales, quats,
    opacity_logits, sh), the opening ``camera`` and the ``background`` colour (RGB 0..1). A
    viser server is started on a free loopback port to record it, and stopped."""
    rgb, opacity = colours(params["sh"], params["opacity_logits"])
    quiet = contextlib.redirect_stdout(io.StringIO())    # viser prints its address and stop
    with quiet:
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = server.scene
        scene.set_up_direction(tuple(camera["scene_up"]))
        bg = np.round(255 * np.clip(np.asarray(background, np.float64), 0, 1)).astype(np.uint8)
        scene.set_background_image(np.broadcast_to(bg, (BACKGROUND_SIDE, BACKGROUND_SIDE, 3))
                                   .copy(), format="png")
        scene.add_gaussian_splats("/splats", centers=np.asarray(params["means"], np.float32),
                                  covariances=covariances(params["log_scales"], params["quats"]),
                                  rgbs=rgb, opacities=opacity)
        cam = server.initial_camera
        cam.position = tuple(camera["position"])
        cam.look_at = tuple(camera["look_at"])
        cam.up = tuple(camera["up"])
        cam.fov = float(camera["fov"])
        cam.near = float(camera["near"])
        cam.far = float(camera["far"])
        return server.get_scene_serializer().serialize()
    finally:
        with quiet:
            server.stop()


def page(viser) -> str:
    """viser's built client with PLAYBACK_SCRIPT before the end of its head."""
    html = (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text("utf-8")
    at = html.index("</head>")
    return html[:at] + PLAYBACK_SCRIPT.format(scene=SCENE_FILE) + html[at:]


def write_web(model, state, out, views) -> str:
    """Write the folder ``out`` (new or empty; module doc) of the splat ``model`` loaded with
    checkpoint ``state``, built under a temporary name and renamed into place (an error
    leaves nothing); ``views`` (interface.ExportViews) the cameras it may open at. Returns the
    line to print."""
    from .model import viewer_params
    viser = need_viser()
    out = check_web_dir(out)
    params, note = viewer_params(model)
    if len(params["means"]) == 0:
        raise WebExportError(f"--web {out}: the scene has no Gaussians to show")
    camera = opening_camera(state, params["means"], views)
    scene = recording(viser, params, camera, model.background)
    html = page(viser)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_dir(out) as tmp:
        tmp.mkdir()
        (tmp / SCENE_FILE).write_bytes(scene)
        (tmp / PAGE_FILE).write_text(html, "utf-8")
    n, degree = len(params["means"]), model.config.sh_degree
    dropped = f" (of SH degree {degree}: view-dependent colour dropped)" if degree else ""
    return (f"saved {out}/ (viser {viser.__version__} web client): {PAGE_FILE} "
            f"{len(html.encode()) / 1e6:.2f} MB, {SCENE_FILE} {len(scene) / 1e6:.2f} MB, "
            f"{n} Gaussians, colour SH degree 0{dropped}{note}; opens at {camera['what']}; "
            f"serve it with `python -m http.server -d {out}` and open http://localhost:8000/")
