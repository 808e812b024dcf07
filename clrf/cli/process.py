"""The ``clrf process`` subcommand: its arguments and handler (the work is in clrf/data/process.py)."""
from __future__ import annotations


def add_process_parser(sub):
    """Add ``process`` to the subparsers ``sub`` of the clrf CLI."""
    from ..data.process import EXHAUSTIVE_MAX, ProcessOptions
    d = ProcessOptions()
    p = sub.add_parser(
        "process", help="pose a video or a folder of photos with COLMAP (needs clrf[process]) "
                        "and write a scene `clrf train --data` reads")
    p.add_argument("source", metavar="VIDEO|IMAGE_DIR",
                   help="a video file (needs imageio-ffmpeg) or a folder of images")
    p.add_argument("--out", required=True,
                   help="scene folder to write (images/, sparse/0/, clrf_process.json); built "
                        "beside it and renamed into place only when every stage succeeded")
    p.add_argument("--frames", type=int, default=d.frames,
                   help=f"video: frames to keep, the sharpest (variance of the Laplacian) of "
                        f"each of this many equal time windows (default {d.frames})")
    p.add_argument("--matcher", choices=["auto", "sequential", "exhaustive"], default=d.matcher,
                   help=f"feature matching: sequential (neighbouring frames) or exhaustive (all "
                        f"pairs); auto: sequential for a video or more than {EXHAUSTIVE_MAX} "
                        f"images, else exhaustive")
    p.add_argument("--overlap", type=int, default=d.overlap,
                   help=f"sequential matcher: successors matched per frame (default {d.overlap})")
    p.add_argument("--camera-model", default=d.camera_model,
                   help=f"COLMAP camera model estimated before undistorting to PINHOLE, e.g. "
                        f"SIMPLE_RADIAL, OPENCV, PINHOLE (default {d.camera_model})")
    p.add_argument("--max-features", type=int, default=d.max_features,
                   help=f"SIFT features per image (default {d.max_features})")
    p.add_argument("--min-fraction", type=float, default=d.min_fraction,
                   help=f"fail when fewer than this fraction of the frames register "
                        f"(default {d.min_fraction})")
    p.add_argument("--threads", type=int, default=d.threads,
                   help="COLMAP threads (default -1: all cores)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_process)
    return p


def cmd_process(a):
    from ..data.process import ProcessOptions, process
    opt = ProcessOptions(frames=a.frames, matcher=a.matcher, overlap=a.overlap,
                         camera_model=a.camera_model, max_features=a.max_features,
                         min_fraction=a.min_fraction, threads=a.threads, force=a.force)
    process(a.source, a.out, opt)
    return 0
