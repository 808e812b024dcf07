"""Peer implementations of clrf's grid render for tools/bench.py (optional dependencies).

Each peer class takes ``(links, density_rows, sh_rows, origins, dirs, params, target)`` in
clrf's layout and conventions (cl/grid_render.cl header) and offers ``forward()`` -> rgb
[n, 3] numpy and ``forward_backward()`` -> (grad_density [N], grad_sh [N, C]) of the fused
MSE loss ``sum |rgb - target|^2 / n`` (clrf's GRAD_MODE 1 with loss_scale 1/n).
Written for the measurement; no code from other projects.
"""
