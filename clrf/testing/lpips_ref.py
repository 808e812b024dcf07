"""Float64 numpy reference of LPIPS v0.1 (clrf.training.perceptual), for tests.

Written from the published definition, independently of clrf.training.perceptual's torch code:
x in [0, 1] -> 2 x - 1 -> (x - shift) / scale per channel -> backbone (convolutions as
im2col matrix products, ReLU, max pooling without padding, floor sizes) -> at each of the five
taps f / (sqrt(sum_c f^2) + 1e-10) -> (f_x - f_y)^2 weighted by the linear weights w_l and summed
over channels -> mean over the tap's pixels -> sum over taps.

Backbone weights: a dict of torchvision's names ("features.<i>.weight" [O, C, k, k] and
"features.<i>.bias" [O]) to numpy arrays; linear weights: "lin<l>.model.1.weight" [1, C, 1, 1].
"""
from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

# torchvision's layer lists: (index, op, kernel, stride, padding); ReLU after every conv
ALEXNET = [(0, "conv", 11, 4, 2), (2, "pool", 3, 2, 0), (3, "conv", 5, 1, 2), (5, "pool", 3, 2, 0),
           (6, "conv", 3, 1, 1), (8, "conv", 3, 1, 1), (10, "conv", 3, 1, 1)]
ALEXNET_CHANNELS = {0: 64, 3: 192, 6: 384, 8: 256, 10: 256}
ALEXNET_TAPS = (0, 3, 6, 8, 10)          # the conv whose ReLU output is tapped
VGG16_CHANNELS = [64, 64, None, 128, 128, None, 256, 256, 256, None, 512, 512, 512, None,
                  512, 512, 512]
SHIFT = np.array([-0.030, -0.088, -0.188])
SCALE = np.array([0.458, 0.448, 0.450])


def vgg16_layers():
    """(layers as in ALEXNET, {conv index: out channels}, taps) of VGG-16's features."""
    layers, chans, taps, i = [], {}, [], 0
    for j, c in enumerate(VGG16_CHANNELS):
        if c is None:
            layers.append((i, "pool", 2, 2, 0))
            i += 1
        else:
            layers.append((i, "conv", 3, 1, 1))
            chans[i] = c
            nxt = VGG16_CHANNELS[j + 1] if j + 1 < len(VGG16_CHANNELS) else None
            if nxt is None:                   # the last conv of each block: relu1_2 .. relu5_3
                taps.append(i)
            i += 2
    return layers, chans, tuple(taps)


def backbone_shapes(net: str) -> dict:
    """torchvision name -> shape of every backbone parameter of ``net`` ('alex' or 'vgg')."""
    layers, chans, _ = (ALEXNET, ALEXNET_CHANNELS, ALEXNET_TAPS) if net == "alex" else \
        vgg16_layers()
    out, c_in = {}, 3
    for i, op, k, _, _ in layers:
        if op == "conv":
            out[f"features.{i}.weight"] = (chans[i], c_in, k, k)
            out[f"features.{i}.bias"] = (chans[i],)
            c_in = chans[i]
    return out


def _conv(x, w, b, stride, pad):
    """x [C, H, W], w [O, C, k, k] -> [O, H', W'] (cross-correlation, zero padding)."""
    k = w.shape[-1]
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    win = sliding_window_view(xp, (k, k), axis=(1, 2))[:, ::stride, ::stride]   # C, H', W', k, k
    return np.tensordot(w, win, axes=([1, 2, 3], [0, 3, 4])) + b[:, None, None]


def _pool(x, k, stride):
    return sliding_window_view(x, (k, k), axis=(1, 2))[:, ::stride, ::stride].max((-2, -1))


def features(x, net, weights):
    """The five tapped, ReLU'd activations [C_l, H_l, W_l] of one image x [3, H, W]."""
    layers, _, taps = (ALEXNET, ALEXNET_CHANNELS, ALEXNET_TAPS) if net == "alex" else \
        vgg16_layers()
    out = []
    for i, op, k, s, p in layers:
        if op == "conv":
            x = np.maximum(_conv(x, weights[f"features.{i}.weight"],
                                 weights[f"features.{i}.bias"], s, p), 0.0)
            if i in taps:
                out.append(x)
                if len(out) == len(taps):
                    break
        else:
            x = _pool(x, k, s)
    return out


def lpips_ref(img, ref, net, backbone: dict, linear: dict) -> float:
    """LPIPS distance of two [H, W, 3] images in [0, 1], in float64."""
    bb = {k: np.asarray(v, np.float64) for k, v in backbone.items()}
    fs = []
    for im in (img, ref):
        x = np.asarray(im, np.float64).transpose(2, 0, 1) * 2.0 - 1.0
        x = (x - SHIFT[:, None, None]) / SCALE[:, None, None]
        fs.append(features(x, net, bb))
    total = 0.0
    for l, (a, b) in enumerate(zip(*fs)):
        a = a / (np.sqrt((a * a).sum(0, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b * b).sum(0, keepdims=True)) + 1e-10)
        w = np.asarray(linear[f"lin{l}.model.1.weight"], np.float64).reshape(-1)
        total += float(np.einsum("c,chw->hw", w, (a - b) ** 2).mean())
    return total
