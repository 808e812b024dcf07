"""LPIPS (learned perceptual image patch similarity, v0.1) on the CPU with torch, never downloading.

LPIPS(x, y) = sum_l mean_{h,w} sum_c w_lc (f_l(x) - f_l(y))_hwc^2 for images x, y scaled to
[-1, 1] and shifted / scaled per channel (shift (-0.030, -0.088, -0.188), scale (0.458, 0.448,
0.450)), with f_l the ImageNet backbone's activations at five ReLUs, each unit-normalised over
channels (f / (|f| + 1e-10)), and w_l >= 0 the learned linear weights. Backbones:

- ``alex``: AlexNet (relu1..relu5; channels 64, 192, 384, 256, 256), as most tables use;
- ``vgg``: VGG-16 (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; 64, 128, 256, 512, 512), as the
  NeRF paper's Blender table.

Two sets of weights are needed and neither is fetched at run time:

1. the linear weights, shipped inside the ``lpips`` PyPI package (``weights/v0.1/NET.pth``); the
   package is found without importing it (importing it needs torchvision);
2. the backbone's ImageNet weights, torchvision's files ``alexnet-owt-7be5be79.pth`` /
   ``vgg16-397923af.pth``. No PyPI package ships them; they are looked up, in order, at the
   ``backbone=`` argument, in the folder ``$CLRF_LPIPS_WEIGHTS``, and in torch's hub cache
   (``$TORCH_HOME/hub/checkpoints``, by default ``~/.cache/torch/hub/checkpoints``), where a
   torchvision that had network access leaves them. Copy them there from such a machine.

Anything missing raises ``LpipsUnavailable`` whose message says what and how to fix it.
The networks are built here with torch.nn (no torchvision), with torchvision's layer indices so
its state dicts load unchanged.
"""
from __future__ import annotations

import functools
import importlib.util
import os
from pathlib import Path

import numpy as np

NETS = ("alex", "vgg")
BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
WEIGHTS_ENV = "CLRF_LPIPS_WEIGHTS"
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORM_EPS = 1e-10
# (kind, args) per torchvision features index; taps: indices after which a feature is taken
_ALEX = [("conv", 3, 64, 11, 4, 2), ("relu",), ("pool", 3, 2), ("conv", 64, 192, 5, 1, 2),
         ("relu",), ("pool", 3, 2), ("conv", 192, 384, 3, 1, 1), ("relu",),
         ("conv", 384, 256, 3, 1, 1), ("relu",), ("conv", 256, 256, 3, 1, 1), ("relu",)]
_ALEX_TAPS = (1, 4, 7, 9, 11)
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (3, 8, 15, 22, 29)
INSTALL_HINT = "install the optional extra: bash tools/setup.sh eval (torch CPU + lpips)"


class LpipsUnavailable(RuntimeError):
    """LPIPS cannot be computed here; the message says why and how to fix it."""


def _vgg_layers():
    layers, c = [], 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(("pool", 2, 2))
        else:
            layers += [("conv", c, v, 3, 1, 1), ("relu",)]
            c = v
    return layers


def _torch():
    try:
        import torch
    except ImportError as e:
        raise LpipsUnavailable(f"LPIPS unavailable: torch is not installed ({e}); "
                               f"{INSTALL_HINT}") from None
    return torch


def linear_weights_path(net: str) -> Path:
    """The lpips package's shipped linear-layer file for ``net`` (package not imported)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        raise LpipsUnavailable(f"LPIPS unavailable: the lpips package (its linear-layer weights) "
                               f"is not installed; {INSTALL_HINT}")
    p = Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / f"{net}.pth"
    if not p.is_file():
        raise LpipsUnavailable(f"LPIPS unavailable: {p} is missing from the lpips package; "
                               f"reinstall it (pip install --force-reinstall --no-deps lpips)")
    return p


def backbone_path(net: str, backbone=None) -> Path:
    """Where the ImageNet backbone file for ``net`` is: ``backbone`` (a file), else
    $CLRF_LPIPS_WEIGHTS/<file>, else torch's hub cache; LpipsUnavailable when none exists."""
    name = BACKBONE_FILES[_check_net(net)]
    if backbone is not None:
        p = Path(backbone)
        if not p.is_file():
            raise LpipsUnavailable(f"LPIPS unavailable: backbone file {p} does not exist; pass "
                                   f"torchvision's {name}")
        return p
    tried = []
    if os.environ.get(WEIGHTS_ENV):
        tried.append(Path(os.environ[WEIGHTS_ENV]) / name)
    torch = _torch()
    tried.append(Path(torch.hub.get_dir()) / "checkpoints" / name)
    for p in tried:
        if p.is_file():
            return p
    raise LpipsUnavailable(
        f"LPIPS unavailable: the {net} backbone's ImageNet weights ({name}) are not on this "
        f"machine (looked in {', '.join(str(p) for p in tried)}); clrf never downloads them. "
        f"Copy torchvision's {name} from a machine with network access into "
        f"${WEIGHTS_ENV} or {tried[-1].parent}")


def _check_net(net):
    if net not in NETS:
        raise ValueError(f"lpips net: expected one of {NETS}, got {net!r}")
    return net


class _Lpips:
    """The backbone (torch.nn.Sequential with torchvision's indices) plus the linear weights."""

    def __init__(self, net, backbone_file, linear_file):
        torch = _torch()
        nn = torch.nn
        spec = _ALEX if net == "alex" else _vgg_layers()
        self.taps = _ALEX_TAPS if net == "alex" else _VGG_TAPS
        mods = []
        for kind, *a in spec:
            if kind == "conv":
                mods.append(nn.Conv2d(a[0], a[1], a[2], stride=a[3], padding=a[4]))
            elif kind == "relu":
                mods.append(nn.ReLU(inplace=False))
            else:
                mods.append(nn.MaxPool2d(a[0], stride=a[1]))
        self.features = nn.Sequential(*mods).eval()
        self._load_backbone(torch, backbone_file)
        self.lin = self._load_linear(torch, linear_file)
        self.shift = torch.tensor(SHIFT, dtype=torch.float32).view(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, dtype=torch.float32).view(1, 3, 1, 1)

    def _load_backbone(self, torch, path):
        try:
            sd = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
            raise LpipsUnavailable(f"LPIPS unavailable: {path}: unreadable as a torch state dict "
                                   f"({type(e).__name__}: {e})") from None
        want = self.features.state_dict()
        got = {k[len("features."):]: v for k, v in sd.items() if k.startswith("features.")}
        bad = [k for k in want if k not in got or tuple(got[k].shape) != tuple(want[k].shape)]
        if bad:
            raise LpipsUnavailable(f"LPIPS unavailable: {path}: not torchvision's backbone for "
                                   f"this net (features.{bad[0]} missing or of another shape)")
        self.features.load_state_dict({k: got[k] for k in want})

    def _load_linear(self, torch, path):
        sd = torch.load(path, map_location="cpu", weights_only=True)
        lin = []
        for i, tap in enumerate(self.taps):
            w = sd.get(f"lin{i}.model.1.weight")
            c = self.features[tap - 1].out_channels
            if w is None or tuple(w.shape) != (1, c, 1, 1):
                raise LpipsUnavailable(f"LPIPS unavailable: {path}: lin{i}.model.1.weight missing "
                                       f"or not of shape (1, {c}, 1, 1); reinstall lpips")
            lin.append(w.reshape(1, c, 1, 1).float())
        return lin

    def __call__(self, x, y):
        """x, y: float32 tensors [N, 3, H, W] in [-1, 1] -> [N] distances."""
        torch = _torch()
        with torch.no_grad():
            fx, fy = self._feats((x - self.shift) / self.scale), self._feats((y - self.shift)
                                                                            / self.scale)
            total = 0
            for a, b, w in zip(fx, fy, self.lin):
                a = a / (torch.sqrt((a * a).sum(1, keepdim=True)) + NORM_EPS)
                b = b / (torch.sqrt((b * b).sum(1, keepdim=True)) + NORM_EPS)
                total = total + ((a - b) ** 2 * w).sum(1).mean((1, 2))
        return total

    def _feats(self, x):
        out, last = [], self.taps[-1]
        for i, m in enumerate(self.features):
            x = m(x)
            if i in self.taps:
                out.append(x)
            if i == last:
                break
        return out


@functools.lru_cache(maxsize=4)
def _model(net, backbone_file, linear_file, mtime):
    return _Lpips(net, backbone_file, linear_file)


def lpips_model(net="alex", backbone=None):
    """The LPIPS network for ``net`` (cached); LpipsUnavailable when it cannot be built here."""
    _check_net(net)
    _torch()
    lin = linear_weights_path(net)
    bb = backbone_path(net, backbone)
    return _model(net, str(bb), str(lin), bb.stat().st_mtime_ns)


def lpips(img, ref, net="alex", backbone=None) -> float:
    """LPIPS distance between two [H, W, 3] images in [0, 1] (lower is closer; 0 for equal images).

    img is clipped to [0, 1]; both are scaled to [-1, 1] (2 v - 1) and laid out [1, 3, H, W].
    Raises LpipsUnavailable (message: why and how to fix) when torch, the lpips package's weights
    or the backbone's ImageNet weights are missing.
    """
    a = np.clip(np.asarray(img, np.float32), 0, 1)
    b = np.asarray(ref, np.float32)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"lpips: expected two [H, W, 3] images, got {a.shape} and {b.shape}")
    model = lpips_model(net, backbone)
    torch = _torch()
    t = [torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1)[None] * 2 - 1)) for v in (a, b)]
    return float(model(*t)[0])


def lpips_status(net="alex", backbone=None) -> str | None:
    """None when LPIPS with ``net`` can be computed here, else the reason (a full sentence)."""
    try:
        lpips_model(net, backbone)
    except LpipsUnavailable as e:
        return str(e)
    return None
