"""clrf.runtime.atomicfile: the one way clrf replaces a file (a temporary file in the same folder,
then a rename), and a scan that no other module of the package renames a temporary file itself."""
import ast
from pathlib import Path

import numpy as np
import pytest

import clrf
from clrf.runtime.atomicfile import atomic_dir, atomic_path, write_bytes, write_text


def _names(folder):
    return sorted(p.name for p in Path(folder).iterdir())


def test_replaces_the_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "frame.png"
    p.write_text("old")
    with atomic_path(p) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith("frame.png.tmp")
        assert tmp.suffix == ".png" and not tmp.exists()      # the caller creates it
        tmp.write_text("new")
    assert p.read_text() == "new"
    assert _names(tmp_path) == ["frame.png"]
    with atomic_path(tmp_path / "new.json", sync=False) as tmp:   # no file there before
        tmp.write_text("{}")
    assert _names(tmp_path) == ["frame.png", "new.json"]


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt])
def test_an_exception_keeps_the_old_file_and_removes_the_temporary(tmp_path, exc):
    p = tmp_path / "ckpt.npz"
    p.write_text("old")
    with pytest.raises(exc):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise exc()
    assert p.read_text() == "old"
    assert _names(tmp_path) == ["ckpt.npz"]


def test_a_failed_rename_raises_and_leaves_nothing(tmp_path):
    (tmp_path / "eval.json").mkdir()                   # the rename onto a folder fails
    with pytest.raises(OSError):
        write_text(tmp_path / "eval.json", "{}")
    assert _names(tmp_path) == ["eval.json"] and (tmp_path / "eval.json").is_dir()


def test_writers_that_pick_the_format_by_the_extension(tmp_path):
    z = np.arange(6, dtype=np.float32).reshape(2, 3)
    with atomic_path(tmp_path / "depth.npy") as tmp:   # np.save appends .npy to other names
        np.save(tmp, z)
    assert np.array_equal(np.load(tmp_path / "depth.npy"), z)
    with atomic_path(tmp_path / "clip.mov", suffix=".mp4") as tmp:
        assert tmp.suffix == ".mp4"
        tmp.write_bytes(b"x")
    iio = pytest.importorskip("imageio.v3")
    img = np.full((4, 5, 3), 200, np.uint8)
    with atomic_path(tmp_path / "frame.png") as tmp:
        iio.imwrite(tmp, img)
    assert np.array_equal(iio.imread(tmp_path / "frame.png"), img)
    assert _names(tmp_path) == ["clip.mov", "depth.npy", "frame.png"]


def test_write_text_and_bytes_write_exactly(tmp_path):
    write_text(tmp_path / "metrics.csv", "a,b\r\n1,2\r\n")
    assert (tmp_path / "metrics.csv").read_bytes() == b"a,b\r\n1,2\r\n"   # no translation
    write_bytes(tmp_path / "b.bin", b"\x00\x01", sync=False)
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"


def test_a_run_folder_cleanup_matches_the_temporary_names(tmp_path):
    """A process killed inside the block leaves its temporary file; remove_stale_temps (run at
    the next start in the run folder) matches it, in the folder and in renders/."""
    from clrf.outputs.rundir import remove_stale_temps
    (tmp_path / "renders").mkdir()
    held, left = [], []
    for name in ("ckpt.npz", "ckpt.it000000010.rank0of2.npz", "config.json", "metrics.csv",
                 "error_vs_time.png", "renders/test_000.png"):
        (tmp_path / name).write_text("complete")
        held.append(atomic_path(tmp_path / name))
        tmp = held[-1].__enter__()                           # never exited: killed
        tmp.write_text("half")
        left.append(tmp)
    assert len(remove_stale_temps(tmp_path)) == len(left)
    assert not any(p.exists() for p in left)
    assert _names(tmp_path / "renders") == ["test_000.png"]


def test_atomic_dir_replaces_a_folder(tmp_path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as new:
            new.mkdir()
            (new / "half.txt").write_text("x")
            raise RuntimeError()
    assert _names(tmp_path) == ["scene"] and _names(out) == ["old.txt"]
    with atomic_dir(out) as new:
        assert new.parent == tmp_path and not new.exists()
        new.mkdir()
        (new / "images").mkdir()
    assert _names(tmp_path) == ["scene"] and _names(out) == ["images"]
    with atomic_dir(tmp_path / "fresh") as new:        # nothing there before
        new.mkdir()
    assert _names(tmp_path) == ["fresh", "scene"]


# --- the scan: only clrf/runtime/atomicfile.py renames a temporary file ----------------------

RENAMES = ("replace", "rename", "renames")
TEMPFILES = ("mkstemp", "mktemp")


def renames(source: str) -> list:
    """The calls in ``source`` that rename a file or make a named temporary file by hand:
    os.replace / os.rename / os.renames (also imported by name), pathlib's X.replace(target) /
    X.rename(target) (one argument: str.replace takes two), tempfile.mkstemp / mktemp."""
    hits = []
    for n in ast.walk(ast.parse(source)):
        if isinstance(n, ast.ImportFrom) and n.module in ("os", "tempfile"):
            hits += [f"from {n.module} import {a.name}" for a in n.names
                     if a.name in RENAMES + TEMPFILES]
        if not isinstance(n, ast.Call):
            continue
        f = n.func
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
        if name in TEMPFILES:
            hits.append(ast.unparse(n))
        elif isinstance(f, ast.Attribute) and name in RENAMES and (
                (isinstance(f.value, ast.Name) and f.value.id == "os")
                or (len(n.args) == 1 and not n.keywords)):
            hits.append(ast.unparse(n))
    return hits


# the sites clrf had before atomicfile.py, as they were written
OLD_SITES = [
    "os.replace(tmp, path)",
    "os.rename(tmp, path)",
    "tmp.replace(out / f'{name}.npy')",
    "Path(str(png_path) + '.tmp.png').replace(png_path)",
    "final.rename(out)",
    "fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix='.tmp')",
    "from os import replace",
]
NOT_RENAMES = [
    "name = 'a.b'.replace('.', '_')",
    "cfg = dataclasses.replace(cfg, iterations=3)",
    "t = time.replace(hour=1)",
    "d = tempfile.TemporaryDirectory(prefix='clrf-')",
    "p = tempfile.mkdtemp(dir=out.parent)",      # a scratch folder, deleted, never renamed
]


@pytest.mark.parametrize("src", OLD_SITES)
def test_the_scan_catches_a_hand_written_rename(src):
    assert renames(src), src


@pytest.mark.parametrize("src", NOT_RENAMES)
def test_the_scan_ignores_other_replaces(src):
    assert not renames(src), src


def test_only_atomicfile_renames_temporary_files():
    root = Path(clrf.__file__).parent          # the installed package the tests import
    files = sorted(root.rglob("*.py"))
    helper = root / "runtime" / "atomicfile.py"
    assert len(files) > 50 and helper in files
    assert renames(helper.read_text()), "the scan matches nothing, not even the helper's own"
    found = {str(f.relative_to(root)): renames(f.read_text()) for f in files if f != helper}
    found = {k: v for k, v in found.items() if v}
    assert not found, ("write through clrf.runtime.atomicfile (atomic_path, write_text, "
                       f"write_bytes, atomic_dir) instead of renaming by hand: {found}")
