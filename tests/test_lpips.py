"""LPIPS: its absence is stated, never silent; with a backbone of random weights saved to a file
(ImageNet weights cannot be fetched here), clrf's LPIPS equals the lpips package's own forward,
which checks the image scaling to [-1, 1], the channel layout, the per-channel shift / scale,
the unit normalisation, the linear weights and the spatial mean."""
import numpy as np
import pytest

from clrf.training.metrics import LpipsUnavailable, lpips, lpips_status
from clrf.training.perceptual import BACKBONE_FILES
from clrf.testing.lpips_ref import backbone_shapes, lpips_ref
from clrf.testing.tolerances import LPIPS_F64_RTOL, LPIPS_REF_ATOL


def _pair(seed, h=64, w=48):
    rng = np.random.default_rng(seed)
    a = rng.random((h, w, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    return a, b


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_absence_is_stated(tmp_path, monkeypatch, net):
    monkeypatch.setenv("CLRF_LPIPS_WEIGHTS", str(tmp_path / "empty"))
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    a, b = _pair(0)
    with pytest.raises(LpipsUnavailable) as e:
        lpips(a, b, net)
    msg = str(e.value)
    assert msg.startswith("LPIPS unavailable: ")
    # whichever piece is missing here is named, with the fix
    assert ("torch is not installed" in msg or "lpips package" in msg
            or (BACKBONE_FILES[net] in msg and "never downloads" in msg
                and str(tmp_path / "empty") in msg)), msg
    assert "setup.sh eval" in msg or "Copy torchvision's" in msg
    assert lpips_status(net) == msg
    with pytest.raises(LpipsUnavailable) as e2:
        lpips(a, b, net, backbone=tmp_path / "nothing.pth")
    if BACKBONE_FILES[net] in msg:       # torch and lpips are there: the file itself is named
        assert "nothing.pth does not exist" in str(e2.value)
    else:
        assert str(e2.value) == msg


def _torch_and_linear(net):
    torch = pytest.importorskip("torch", reason="the 'eval' extra (torch) is not installed: "
                                                "bash tools/setup.sh eval")
    from clrf.training.perceptual import linear_weights_path
    try:
        path = linear_weights_path(net)
    except LpipsUnavailable as e:
        pytest.skip(str(e))
    lin = torch.load(path, map_location="cpu", weights_only=True)
    return torch, {k: v.numpy() for k, v in lin.items()}


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_float64_reference(tmp_path, net):
    """Against clrf/testing/lpips_ref.py (numpy, float64), with a random backbone (He-scaled
    weights, small biases) saved under torchvision's names; runs wherever torch and the lpips
    package's weight files are installed (no torchvision needed)."""
    torch, lin = _torch_and_linear(net)
    rng = np.random.default_rng(11)
    sd = {k: (rng.normal(0, np.sqrt(2 / np.prod(s[1:])), s) if len(s) > 1
              else rng.normal(0, 0.05, s)).astype(np.float32)
          for k, s in backbone_shapes(net).items()}
    path = tmp_path / "backbone.pth"
    torch.save({k: torch.from_numpy(v) for k, v in sd.items()}, path)
    for seed, noise in ((0, 0.05), (1, 0.2)):
        rng2 = np.random.default_rng(seed)
        a = rng2.random((64, 48, 3)).astype(np.float32)
        b = np.clip(a + rng2.normal(0, noise, a.shape), 0, 1).astype(np.float32)
        want = lpips_ref(a, b, net, sd, lin)
        got = lpips(a, b, net, backbone=path)
        assert abs(got - want) <= LPIPS_F64_RTOL * want, (got, want)
        # the prediction is clipped to [0, 1] first, as for PSNR / SSIM
        assert lpips(a * 1.5 - 0.25, b, net, backbone=path) == pytest.approx(
            lpips_ref(np.clip(a * 1.5 - 0.25, 0, 1), b, net, sd, lin), rel=LPIPS_F64_RTOL)


def _reference(net):
    torch = pytest.importorskip("torch", reason="the 'eval' extra (torch) is not installed: "
                                                "bash tools/setup.sh eval")
    try:
        import lpips as lp
    except Exception as e:   # noqa: BLE001 - torchvision beside a CPU torch fails to import
        pytest.skip(f"the lpips package does not import here ({type(e).__name__}: {e}); it "
                    f"needs a torchvision that matches torch (a CUDA build of torch 2.14.1 with "
                    f"torchvision 0.29.1 on this machine kind)")
    torch.manual_seed(3)
    return torch, lp.LPIPS(net=net, pnet_rand=True, verbose=False).eval()


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_matches_lpips_package(tmp_path, net):
    torch, ref = _reference(net)
    # the reference's random backbone, under torchvision's key names (features.<index>.*)
    sd = {"features." + k.split(".", 1)[1]: v for k, v in ref.net.state_dict().items()}
    path = tmp_path / BACKBONE_FILES[net]
    torch.save(sd, path)
    for seed in (0, 1):
        a, b = _pair(seed)
        ta, tb = (torch.from_numpy(x.transpose(2, 0, 1)[None].copy()) for x in (a, b))
        with torch.no_grad():
            want = float(ref(ta, tb, normalize=True))
        got = lpips(a, b, net, backbone=path)
        assert abs(got - want) <= LPIPS_REF_ATOL, (got, want)
        assert want > 10 * LPIPS_REF_ATOL
        assert lpips(a, a, net, backbone=path) == pytest.approx(0.0, abs=LPIPS_REF_ATOL)
    # the folder in $CLRF_LPIPS_WEIGHTS is found the same way
    import os
    os.environ["CLRF_LPIPS_WEIGHTS"] = str(tmp_path)
    try:
        assert lpips_status(net) is None
        assert lpips(a, b, net) == pytest.approx(got, abs=1e-7)
    finally:
        del os.environ["CLRF_LPIPS_WEIGHTS"]
    # other backbone weights give another distance: the file's weights are the ones used
    # (perturbed, not rescaled: the unit normalisation of each layer hides a common scale)
    gen = torch.Generator().manual_seed(5)
    sd2 = {k: v + 0.5 * v.std() * torch.randn(v.shape, generator=gen) for k, v in sd.items()}
    torch.save(sd2, tmp_path / "other.pth")
    assert abs(lpips(a, b, net, backbone=tmp_path / "other.pth") - got) > 10 * LPIPS_REF_ATOL


def test_wrong_backbone_file_is_refused(tmp_path):
    torch = pytest.importorskip("torch", reason="the 'eval' extra (torch) is not installed: "
                                                "bash tools/setup.sh eval")
    from clrf.training.perceptual import linear_weights_path
    try:
        linear_weights_path("alex")
    except LpipsUnavailable as e:
        pytest.skip(str(e))
    torch.save({"features.0.weight": torch.zeros(2, 2)}, tmp_path / "bad.pth")
    a, b = _pair(0)
    with pytest.raises(LpipsUnavailable, match="features.0.weight missing or of another shape"):
        lpips(a, b, "alex", backbone=tmp_path / "bad.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(LpipsUnavailable, match="unreadable"):
        lpips(a, b, "alex", backbone=tmp_path / "junk.pth")
