"""Every kernel family runs under the Oclgrind simulator's checks with no report.

Oclgrind (Debian ``oclgrind``; ``bash tools/setup.sh impls``) simulates an OpenCL 1.2 device and
reports out-of-bounds accesses, data races between work-items (``OCLGRIND_DATA_RACES``), barrier
divergence and API misuse (``OCLGRIND_CHECK_API``): bugs that PoCL tolerates and a GPU may not.
It is a device of its own here, through a vendors folder that names only its ICD, and runs a
small test of each kernel family (CASES) in a child pytest: grid forward and backward in both
loss modes with touched marks, the MSI background, bricks, grid ops (TV, resample, prune, batch
gather, the ray store's strided read-back, fused loss), the optimisers, encode, sample,
composite and the fused MLP forward and backward (CPU tiles, and the GPU tiling on a small
network), the hash encoding's backward and spatial derivative, the hash march (windows, alive
rays, contraction, each ray's camera gradient), the grid's camera gradient (both shapes) and
its backward through each ray's image transform, the rays of corrected cameras and their
per-image camera gradient sums, Adam over spans and over several buffers in one launch, the
Gaussian splatting projection (forward, backward; anti-aliased; the camera's gradient), the
density strategies' statistics (default) and regularisers and noise (MCMC), the distributed
step's gradient sum, the bilateral grid (slice, both backward passes, the prior and Adam over
every grid), the training images' widening (uint8, float16), binning (pyopencl's scan and
radix sort, clrf's chunked sort) and tile rasteriser (forward, backward), and the hash model's
bounded step (capped offsets, the encoding and the MLP on both tilings reading a device count,
a bounded step with the GPU tiling).
The child's tests must pass and Oclgrind must report nothing.

One API report is not clrf's: pyopencl asks every device for OpenCL 3.0 properties while
building a program and looking up a kernel, and a 1.2 device answers CL_INVALID_VALUE, which
pyopencl handles (``clGetDeviceInfo`` / ``CL_INVALID_VALUE`` / ``param_name``). Those reports
are counted apart and must be the only API reports. Nor are pyopencl's generated scan kernels
(``scan_lev1``, ``scan_lev2``, ``final_update``; clrf/grid/ops.py uses GenericScanKernel to
number the kept voxels): Oclgrind reports read-write races on global memory inside
``scan_lev1``, where pyopencl's code reads global data another work-item of the group wrote
with only a local-memory barrier between them. Their results are checked against the
reference by the prune/resample tests. ``--uninitialized`` is not used: Oclgrind
21.10's plugin stops on LLVM's ``freeze`` instruction ("Unsupported instruction: freeze") and
crashes on kernels that add two elements of one vector (clrf/runtime/device_probe.py is_simulator).
"""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_nerf_mlp import SPECS as MLP_SPECS  # noqa: E402
ICD = Path("/usr/lib/oclgrind/liboclgrind-rt-icd.so")

CASES = [
    "tests/test_render.py::test_forward_vs_reference",
    "tests/test_render.py::test_forward_gpu_shape_vs_reference",
    "tests/test_render.py::test_backward_vs_finite_differences",
    "tests/test_render.py::test_backward_per_sample_atomics",
    "tests/test_render.py::test_empty_grid",
    "tests/test_render.py::test_max_weight_vs_reference",
    "tests/test_grid_ops.py::test_update_rows_vs_reference",
    "tests/test_grid_ops.py::test_update_rows_live_columns",
    "tests/test_grid_ops.py::test_tv_grad_vs_reference",
    "tests/test_grid_ops.py::test_resample_vs_reference",
    "tests/test_grid_ops.py::test_prune_vs_reference_and_to_nothing",
    "tests/test_grid_ops.py::test_gather_batch_vs_reference",
    "tests/test_grid_ops.py::test_strided_rays_read_back_from_the_device",
    "tests/test_grid_ops.py::test_fused_mse_and_beta_prior_vs_reference",
    "tests/test_background.py::test_awkward_sizes",
    "tests/test_background.py::test_backward_matches_reference",
    "tests/test_bricks.py::test_partial_kernel_vs_reference",
    # one size (65: past a work-group's worth) of each encoding variant
    *[f"tests/test_nerf_encode.py::test_encode_matches_reference[default-{v}-65]"
      for v in ("10-True", "4-False", "0-True")],
    "tests/test_nerf_encode.py::test_encode_backward_matches_reference",
    "tests/test_nerf_sample.py::test_stratified_matches_reference",
    "tests/test_nerf_sample.py::test_importance_matches_reference",
    "tests/test_nerf_composite.py::test_forward_matches_reference",
    "tests/test_nerf_composite.py::test_backward_matches_reference",
    "tests/test_nerf_composite.py::test_mse_mode_loss_and_gradient",
    # NeRF's per-view corrections: each ray's camera gradient (with accumulate), the composite
    # state, and a whole step through both passes' exposure (exposure_rays_grad accumulating)
    "tests/test_nerf_corrections.py::test_ray_points_backward_matches_twin[default-37-5]",
    "tests/test_nerf_corrections.py::test_composite_state_matches_twin",
    "tests/test_nerf_corrections.py::"
    "test_exposure_gradients_of_both_passes_match_the_chain[default-True]",
    # every network of SPECS at 37 rows (a partial tile), and an empty launch; the sizes
    # between change no code path the simulator's checks see
    *[f"tests/test_nerf_mlp.py::test_{pass_}_matches_reference[default-37-{name}]"
      for pass_ in ("forward", "backward") for name in MLP_SPECS],
    f"tests/test_nerf_mlp.py::test_forward_matches_reference[default-0-{next(iter(MLP_SPECS))}]",
    "tests/test_mlp_gpu.py::test_small_network_under_every_pass",
    "tests/test_hash_encode.py::test_backward_matches_reference",
    "tests/test_hash_encode.py::test_dx_matches_twin[default-2-65]",
    "tests/test_hash_kernels.py::test_march_matches_reference",
    "tests/test_hash_kernels.py::test_march_window_and_alive_rays",
    "tests/test_hash_kernels.py::test_march_contracted_matches_reference",
    # each ray's camera gradient (HASH_POSE_GRAD): plain with no SH share, contracted with it
    "tests/test_hash_pose.py::test_ray_grad_matches_twin[default-False-False]",
    "tests/test_hash_pose.py::test_ray_grad_matches_twin[default-True-True]",
    "tests/test_ray_pose.py::test_rays_and_sums_match_the_twin[default-300]",
    # the grid's camera gradient (GRID_POSE_GRAD), both backward shapes, SH degree 2
    "tests/test_grid_pose.py::test_ray_grad_matches_twin[default_path-default-2]",
    "tests/test_grid_pose.py::test_ray_grad_matches_twin[gpu_path-default-2]",
    # the grid backward with each ray's image transform in its loss (RAY_EXPOSURE)
    "tests/test_grid_exposure.py::"
    "test_fused_transform_matches_the_twin[default_path-default-bg_per_ray-clip]",
    "tests/test_grid_exposure.py::test_fused_transform_matches_the_twin[gpu_path-default-bg-plain]",
    "tests/test_hash_kernels.py::test_adam_weight_decay_and_clear_grad",
    "tests/test_hash_kernels.py::test_adam_over_many_spans_in_one_launch",
    "tests/test_hash_kernels.py::test_adam_set_steps_every_buffer_in_one_launch",
    "tests/test_splat_kernels.py::test_splat_project_matches_reference[default-3]",
    "tests/test_splat_kernels.py::test_splat_project_backward_matches_reference[default-3]",
    "tests/test_splat_kernels.py::test_splat_binning_matches_reference[default-40-33-17-rows]",
    "tests/test_splat_kernels.py::test_splat_binning_matches_reference[default-40-33-17-group]",
    "tests/test_splat_kernels.py::"
    "test_splat_rasterize_backward_matches_reference[default-rows-12-33-17]",
    "tests/test_splat_kernels.py::"
    "test_splat_rasterize_backward_matches_reference[default-group-12-33-17]",
    "tests/test_splat_kernels.py::test_splat_rows_shape_with_small_tiles[default-8]",
    "tests/test_splat_kernels.py::"
    "test_splat_rows_backward_copies_match_reference_and_repeat[default-3]",
    "tests/test_splat_kernels.py::test_splat_rows_binning_in_many_chunks[default-None]",
    "tests/test_sort.py::test_key_order_with_many_small_chunks",
    "tests/test_splat_kernels.py::test_splat_opacity_near_one_toy",
    "tests/test_splat_kernels.py::test_splat_no_gaussians",
    "tests/test_splat_loss.py::test_device_loss_matches_twin[default-0.2-37-23-noisy]",
    # the loss's work split: one group, several, and none given, with and without the mask
    *[f"tests/test_splat_loss.py::test_device_work_splits_and_accumulators[default-{m}-{k}]"
      for m in ("False", "True") for k in ("None", "7")],
    "tests/test_splat_exposure.py::test_backward_matches_the_twin[default-257-masked]",
    "tests/test_splat_exposure.py::test_adam_step_matches_the_twin_and_pulls_toward_identity[default]",
    "tests/test_splat_exposure.py::"
    "test_diagonal_adam_trains_gains_and_offsets_only[default-diagonal]",
    "tests/test_splat_exposure.py::"
    "test_diagonal_adam_trains_gains_and_offsets_only[default-gain]",
    "tests/test_splat_exposure.py::"
    "test_clipped_apply_and_backward_match_the_twin[default-7-inward]",
    "tests/test_hash_exposure.py::test_rays_and_their_gradient_match_the_twin[default-71-masked]",
    "tests/test_hash_exposure.py::test_background_share_matches_the_twin[default]",
    "tests/test_hash_exposure.py::test_clipped_rays_match_the_twin_and_its_differences[default-plain]",
    "tests/test_hash_exposure.py::test_each_rays_own_background_matches_the_twin[default-37]",
    "tests/test_hash_exposure.py::test_diagonal_rows_train_gains_and_offsets_only[default-gain]",
    "tests/test_bilateral.py::test_apply_and_backward_match_the_twin"
    "[default-3x97-grid4x3x5-masked]",
    "tests/test_bilateral.py::test_apply_and_backward_match_the_twin"
    "[default-1x1-grid16x16x8-plain]",
    "tests/test_bilateral.py::test_adam_steps_every_grid_as_the_twin_does[default]",
    "tests/test_bilateral.py::test_a_sparse_step_moves_the_trained_views_grid_alone[default]",
    "tests/test_splat_pose.py::test_camera_gradient_on_the_device_matches_the_twin[default-3]",
    "tests/test_splat_antialias.py::test_project_and_backward_match_the_twin[default-3-0.1]",
    "tests/test_splat_antialias.py::test_filter3d_matches_the_twin[default]",
    "tests/test_splat_strategy.py::test_mcmc_reg_matches_the_twin_and_central_differences"
    "[default]",
    "tests/test_splat_strategy.py::test_mcmc_noise_matches_the_twin[default]",
    "tests/test_splat_strategy.py::test_default_statistics_match_the_twin[default-7]",
    "tests/test_splat_kernels.py::test_grad_sum_rounds_as_numpy_float32[default-257]",
    "tests/test_splat_targets.py::test_uint8_images_widen_bit_for_bit[default]",
    "tests/test_splat_targets.py::test_other_images_widen_to_numpys_halves[default-averaged]",
    "tests/test_scan.py::test_capped_offsets_match_clipped_cumsum[100]",
    "tests/test_hash_bounded.py::test_hash_kernels_cover_the_device_count[atomics]",
    "tests/test_hash_bounded.py::test_mlp_passes_cover_the_device_count[softplus-c3-50-33-cpu]",
    "tests/test_hash_bounded.py::test_mlp_passes_cover_the_device_count[softplus-c3-50-33-gpu]",
    "tests/test_hash_bounded.py::test_bounded_step_matches_reference_chain[gpu-False-True]",
]
PYOPENCL_QUERY = re.compile(r"Function: clGetDeviceInfo\s+Error:\s+CL_INVALID_VALUE\s+"
                            r"For argument 'param_name'")
PYOPENCL_KERNELS = ("scan_lev1", "scan_lev2", "final_update")
REPORT = re.compile(r"^(Oclgrind - .*|.*(Invalid (read|write)|data race|Data race|"
                    r"divergence|Uninitialized|OCLGRIND FATAL).*)$", re.MULTILINE)


# the quick tier's share (tests/conftest.py): the grid renderer's forward, both shapes; the
# slow test runs the other cases, so together they run every case once
QUICK_CASES = CASES[:2]


@pytest.mark.quick
def test_the_grid_renderer_is_clean_under_oclgrind(tmp_path):
    _clean_under_oclgrind(tmp_path, QUICK_CASES)


@pytest.mark.slow
def test_every_kernel_family_is_clean_under_oclgrind(tmp_path):
    _clean_under_oclgrind(tmp_path, [c for c in CASES if c not in QUICK_CASES])


def _clean_under_oclgrind(tmp_path, cases):
    if not ICD.exists() or shutil.which("oclgrind") is None:
        pytest.skip("Oclgrind is not installed (`bash tools/setup.sh impls` or "
                    "`apt-get install oclgrind`)")
    vendors = tmp_path / "vendors"
    vendors.mkdir()
    (vendors / "oclgrind.icd").write_text(f"{ICD}\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CLRF_", "OCLGRIND_"))
           or k == "CLRF_TEST_SOURCE_TREE"}
    env.update(OCL_ICD_VENDORS=str(vendors), CLRF_DEVICE="0:0", CLRF_TEST_IMPLS="default",
               OCLGRIND_DATA_RACES="1", OCLGRIND_CHECK_API="1", XDG_CACHE_HOME=str(tmp_path))
    # Oclgrind's device reports every type, GPU among them: test_nerf_mlp.py's cases keep the
    # fused MLP's CPU tiles here; test_mlp_gpu.py's case forces the GPU tiling itself
    env["CLRF_FORCE_GPU_KERNELS"] = "0"
    # -k default: the session device (Oclgrind) only, not the other implementations
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-s", "-p", "no:cacheprovider",
           "-k", "default", *cases]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1500)
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-4000:]
    assert re.search(r"\d+ passed", out.stdout), out.stdout[-2000:]
    # every API report is one of pyopencl's OpenCL 3.0 queries (module doc) ...
    headers = text.count("Oclgrind - OpenCL runtime error detected")
    assert headers == len(PYOPENCL_QUERY.findall(text)), text[-4000:]
    # ... and nothing else is reported: no race, invalid access, divergence
    reports = []
    for m in REPORT.finditer(text):
        if m.group(0) == "Oclgrind - OpenCL runtime error detected":
            continue
        kernel = re.search(r"Kernel: (\w+)", text[m.end():m.end() + 200])
        if kernel and kernel.group(1) in PYOPENCL_KERNELS:
            continue                                   # pyopencl's scan (module doc)
        reports.append(text[m.start():m.end() + 300])
    assert not reports, "\n".join(reports[:10])
