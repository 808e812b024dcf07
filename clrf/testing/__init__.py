"""Float64 numpy references of every kernel (reference.py: grid, reference_nerf.py: NeRF) and of
COLMAP's camera projections (reference_cameras.py), the tolerances the tests hold them to
(tolerances.py), and the `clrf bench` measurement (benchmark.py).

Imported by tests/, tools/ and the `clrf bench` command; never by the train/render/eval path."""
