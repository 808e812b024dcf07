"""Checkpoints: one .npz per run directory, written atomically (temporary file, then rename).

A distributed run (clrf/grid/dist_model.py) writes one file per brick,
``ckpt.it<iteration>.rank<r>of<P>.npz``, and then ``ckpt.npz`` as a manifest naming them
(``save_distributed``); a kill at any moment leaves the previous manifest and its complete set
of brick files. ``load``
merges a manifest's bricks into one whole-grid state (as a single-process run would have
saved it)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..runtime.atomicfile import atomic_path

CKPT_NAME = "ckpt.npz"
BRICK_GLOB = "ckpt.it*.rank*of*.npz"

# Seconds ``save`` pauses inside its write window (temporary file written, not yet renamed):
# 0 in every run. The kill tests set it in the process they start (tests/test_kill.py) to land
# a SIGKILL mid-write deterministically.
WRITE_DELAY = 0.0


class CheckpointError(ValueError):
    pass


def save(path, state: dict):
    """Write ``state`` (numpy arrays and JSON-able values) to ``path`` atomically."""
    path = Path(path)
    arrays = {}
    meta = {}
    for k, v in state.items():
        if isinstance(v, np.ndarray):
            arrays[k] = v
        else:
            meta[k] = v
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        if WRITE_DELAY > 0:     # the temporary file is written, not yet fsynced nor renamed
            time.sleep(WRITE_DELAY)


def brick_file_name(iteration: int, rank: int, ranks: int) -> str:
    return f"ckpt.it{int(iteration):09d}.rank{int(rank)}of{int(ranks)}.npz"


def save_distributed(path, state: dict, comm, reso=None, bricks=None, rows=None):
    """Collective: every rank of ``comm`` writes its part's ``state`` to its own file beside
    ``path``, then rank 0 writes the manifest ``path`` naming them, and removes older part
    files. The layout of the parts: a grid's bricks (the whole grid's ``reso`` and the bricks'
    ``[lo, hi]`` boxes; each state's own box under "brick"), or shards of a table's rows
    (``rows``: {state key: the axis its rows run along}; each state's own place under
    "shard"), which ``load`` joins in rank order."""
    path = Path(path)
    it = int(state["iteration"])
    r, P = comm.Get_rank(), comm.Get_size()
    mine = brick_file_name(it, r, P)
    save(path.parent / mine, state)
    names = comm.gather(mine, root=0)
    if r == 0:
        meta = {k: v for k, v in state.items() if not isinstance(v, np.ndarray)}
        meta.pop("brick", None)
        meta.pop("shard", None)
        if rows is not None:
            meta.update(distributed={"ranks": P, "files": names, "layout": "shards",
                                     "rows": dict(rows)})
        else:
            meta.update(distributed={"ranks": P, "files": names, "reso": list(reso)},
                        bricks=bricks)
        save(path, meta)
        remove_unreferenced_bricks(path.parent)
    comm.Barrier()


def remove_unreferenced_bricks(out) -> list:
    """Delete brick files of run directory ``out`` that its manifest does not name (an older
    set, or an incomplete one a kill left behind); returns them."""
    out = Path(out)
    keep = set()
    man = out / CKPT_NAME
    if man.is_file():
        try:
            keep = set(_read(man).get("distributed", {}).get("files", []))
        except CheckpointError:
            return []   # an unreadable manifest: leave the files for the user
    gone = []
    for p in out.glob(BRICK_GLOB):
        if p.name not in keep and p.is_file():
            p.unlink()
            gone.append(p)
    return gone


def _read(path) -> dict:
    try:
        with np.load(path) as z:
            state = {k: z[k] for k in z.files if k != "__meta__"}
            meta = json.loads(bytes(z["__meta__"]).decode())
    except Exception as e:  # noqa: BLE001 - any decoding failure is a bad checkpoint
        raise CheckpointError(f"checkpoint {path} is unreadable ({e}); it may be from an "
                              f"interrupted copy: use a complete run directory") from None
    state.update(meta)
    return state


def _parts(path, manifest) -> list:
    """The states of a manifest's part files, in rank order."""
    parts = []
    for name in manifest["distributed"]["files"]:
        f = Path(path).parent / name
        if not f.is_file():
            raise CheckpointError(f"checkpoint {path} names brick file {name}, which is missing: "
                                  f"copy the whole run directory")
        parts.append(_read(f))
    return parts


def merge_shards(path, manifest) -> dict:
    """The whole state of a checkpoint whose ranks each held a shard of a table's rows: every
    per-row array of the parts joined in rank order along its axis (the manifest's "rows"),
    everything else the manifest's."""
    rows = manifest["distributed"]["rows"]
    parts = _parts(path, manifest)
    state = {k: v for k, v in manifest.items() if k != "distributed"}
    for key, axis in rows.items():
        have = [st[key] for st in parts if key in st]
        if not have:
            continue
        if len(have) != len(parts):
            raise CheckpointError(f"checkpoint {path}: '{key}' is in {len(have)} of its "
                                  f"{len(parts)} shard files; it may be from an interrupted "
                                  f"copy: use a complete run directory")
        state[key] = np.concatenate(have, axis=int(axis))
    return state


def merge_bricks(path, manifest) -> dict:
    """The whole-grid state of a distributed checkpoint: the owned voxels of every brick file,
    rows in C order of the voxels (as SparseGrid builds them)."""
    d = manifest["distributed"]
    reso = tuple(int(r) for r in d["reso"])
    parts = _parts(path, manifest)
    keys = ("density", "sh", "opt_density", "opt_sh")
    chunks = {k: [] for k in keys}
    gidx = []
    for st in parts:
        b = st["brick"]
        lo, hi = np.array(b["lo"]), np.array(b["hi"])
        own = st["links"][tuple(slice(0, h - l) for l, h in zip(lo, hi))]
        pos = np.argwhere(own >= 0)
        gidx.append(np.ravel_multi_index(tuple((pos + lo).T), reso))
        for k in keys:
            chunks[k].append(st[k][own[own >= 0]])
    gidx = np.concatenate(gidx)
    order = np.argsort(gidx, kind="stable")
    links = np.full(int(np.prod(reso)), -1, np.int32)
    links[gidx[order]] = np.arange(gidx.size, dtype=np.int32)
    state = {k: v for k, v in manifest.items() if k != "distributed"}
    state["links"] = links.reshape(reso)
    for k in keys:
        state[k] = np.concatenate(chunks[k])[order]
    for k in ("bbox", "sh_degree", "stage", "background", "kind"):
        state.setdefault(k, parts[0][k])
    return state


def load(path, brick=None) -> dict:
    """The state saved at ``path`` (a run directory or checkpoint file). A distributed
    checkpoint's bricks are merged into one grid, unless ``brick`` = (rank, ranks) names a
    brick of a run with that many ranks: then only that rank's file is read (with the
    manifest's iteration, seconds and configuration), as a distributed resume does."""
    path = Path(path)
    if path.is_dir():
        path = path / CKPT_NAME
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: pass a run directory written by "
                              f"`clrf train --out DIR` (it holds {CKPT_NAME})")
    state = _read(path)
    if "distributed" in state:
        d = state["distributed"]
        if brick is not None and int(d["ranks"]) == int(brick[1]):
            f = path.parent / d["files"][int(brick[0])]
            if not f.is_file():
                raise CheckpointError(f"checkpoint {path} names brick file {f.name}, which is "
                                      f"missing: copy the whole run directory")
            own = _read(f)
            own.update({k: v for k, v in state.items() if k != "distributed"})
            return own
        state = (merge_shards if d.get("layout") == "shards" else merge_bricks)(path, state)
    return state
