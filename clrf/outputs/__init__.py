"""What a run writes and reads back: checkpoints and run directories (checkpoint.py,
rundir.py), renders of a camera (frames.py, camera_path.py), meshes and point clouds
(export.py, ply.py) and TensorBoard logs (tblog.py)."""
