"""What a user installs is what the tests test.

- The tests themselves run on an install, never on this checkout (tests/conftest.py stops the
  run otherwise), and so do the processes they start.
- Every package under clrf/ is discovered (setup.py), none listed by hand: each folder of
  clrf/ with Python files is a package, every module of the checkout is in the wheel with the
  kernels and the viewer's page, and a package added under clrf/ without touching setup.cfg is
  in the wheel too.
- The wheel, installed into a fresh virtual environment, imports every one of its modules (a
  missing optional dependency may skip a module, a missing clrf module may not) and runs
  `clrf train`, `render`, `eval` and `export` on a short procedural run in a folder outside
  the checkout.
- A broken install (a clrf module removed from it) is reported as an installation error, not
  as a faulty driver, and after a reinstall clrf trains with the same cache folder on the
  device a clean cache picks.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest

import clrf

ROOT = Path(__file__).resolve().parent.parent
BUILD_FILES = ("setup.py", "setup.cfg", "pyproject.toml", "README.md")
SHORT_RUN = ["--max-seconds", "4", "--set", "train.eval_every=100"]


def _build_wheel(src: Path, out: Path) -> Path:
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(out), str(src)], capture_output=True, text=True)
    if r.returncode != 0 and "No module named" in r.stderr and "setuptools" in r.stderr:
        pytest.fail("setuptools missing from the test environment (it is in the 'test' extra)")
    assert r.returncode == 0, r.stderr[-3000:]
    (whl,) = out.glob("clrf-*.whl")
    return whl


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of this checkout."""
    return _build_wheel(ROOT, tmp_path_factory.mktemp("wheel"))


def _checkout_modules() -> set:
    """clrf/... module paths of the checkout (``clrf/grid/model.py``)."""
    return {p.relative_to(ROOT).as_posix() for p in (ROOT / "clrf").rglob("*.py")
            if "__pycache__" not in p.parts}


def test_the_tests_import_the_install():
    where = Path(clrf.__file__).resolve()
    if os.environ.get("CLRF_TEST_SOURCE_TREE") == "1":
        pytest.skip("CLRF_TEST_SOURCE_TREE=1: this run tests the checkout on purpose")
    assert where.parent != (ROOT / "clrf").resolve(), where
    # a child started the way the tests start them, in the checkout, imports the install too
    r = subprocess.run([sys.executable, "-m", "clrf.cli", "--version"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith(f"clrf {clrf.__version__}"), r.stderr
    r = subprocess.run([sys.executable, "-c", "import clrf; print(clrf.__file__)"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert Path(r.stdout.strip()).resolve().parent != (ROOT / "clrf").resolve(), r.stdout


def test_every_folder_of_clrf_is_a_package():
    """Discovery finds packages by their __init__.py: a folder of modules without one would
    be left out of the wheel."""
    for folder in (ROOT / "clrf").rglob("*"):
        if folder.is_dir() and "__pycache__" not in folder.parts and any(folder.glob("*.py")):
            assert (folder / "__init__.py").is_file(), f"{folder} has modules but no __init__.py"


@pytest.mark.slow
def test_the_wheel_holds_every_module_and_the_kernels(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(_checkout_modules() - names)
    assert not missing, f"modules of the checkout missing from the wheel: {missing}"
    kernels = {f"clrf/cl/{p.name}" for p in (ROOT / "cl").iterdir() if p.suffix in (".cl", ".h")}
    assert kernels and kernels <= names, sorted(kernels - names)
    assert "clrf/viewer/page.html" in names
    assert "clrf/_build_commit.py" in names      # `clrf --version` of an install


@pytest.mark.slow
def test_a_new_package_is_in_the_wheel_without_touching_setup_cfg(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in BUILD_FILES:
        shutil.copy2(ROOT / name, src / name)
    for folder in ("clrf", "cl"):
        shutil.copytree(ROOT / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    new = src / "clrf" / "brand_new" / "deeper"
    new.mkdir(parents=True)
    (new.parent / "__init__.py").write_text('"""A package setup.cfg does not name."""\n')
    (new / "__init__.py").write_text("")
    (new / "module.py").write_text("VALUE = 1\n")
    cfg = (src / "setup.cfg").read_text()
    assert "brand_new" not in cfg
    names = set(zipfile.ZipFile(_build_wheel(src, tmp_path / "out")).namelist())
    assert {"clrf/brand_new/__init__.py", "clrf/brand_new/deeper/__init__.py",
            "clrf/brand_new/deeper/module.py"} <= names


def _clean_env(**kw) -> dict:
    """This environment without PYTHONPATH (which a source-tree run points at the checkout)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(kw)
    return env


def _device_of(stderr: str) -> str:
    """'P:D' of the "clrf: device P:D ..." line a run prints."""
    m = re.search(r"^clrf: device (\d+:\d+) ", stderr, re.MULTILINE)
    assert m, stderr[-3000:]
    return m.group(1)


def _fresh_venv(tmp_path: Path, wheel: Path) -> Path:
    """A new virtual environment with the wheel installed in it; clrf's dependencies come from
    this environment's site-packages, read after the venv's own (a .pth file), so the venv's
    clrf is the wheel's. Returns its python."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], capture_output=True, text=True,
                               check=True).stdout.strip())
    # the wheel first, into the bare venv: with the .pth already there pip would see the clrf
    # of this environment (the one under test) as installed, and skip the wheel
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q",
                        "--no-deps", str(wheel)], capture_output=True, text=True,
                       env=_clean_env())
    assert r.returncode == 0, r.stderr[-3000:]
    ours = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "outer_deps.pth").write_text("\n".join(sorted(ours)) + "\n")
    r = subprocess.run([str(py), "-c", "import clrf; print(clrf.__file__)"],
                       capture_output=True, text=True, cwd=tmp_path, env=_clean_env())
    assert Path(r.stdout.strip()).resolve().is_relative_to(venv.resolve()), r.stdout + r.stderr
    return py


IMPORT_ALL = r"""
import importlib, pathlib, pkgutil, sys
import clrf
bad, skipped = [], []
for m in pkgutil.walk_packages(clrf.__path__, "clrf."):
    if m.name.endswith(".__main__"):    # a command, run when imported
        continue
    try:
        importlib.import_module(m.name)
    except ImportError as e:
        missing = getattr(e, "name", None) or ""
        (bad if missing == "clrf" or missing.startswith("clrf.") or not missing
         else skipped).append(f"{m.name}: {e}")
print("SKIPPED", skipped)
assert not bad, bad
print("IMPORTED", clrf.__file__)
"""


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory):
    """One fresh virtual environment with the wheel, shared by the tests below, and the first
    `clrf train` in it from an empty cache folder (``cache``: the probe figures, verdicts and
    compiled kernels a clean install makes). ``py``, ``cache``, ``work`` (outside the
    checkout), ``env`` and ``first`` (that run's CompletedProcess)."""
    tmp = tmp_path_factory.mktemp("venv")
    py = _fresh_venv(tmp, wheel)
    cache = tmp / "cache"
    env = _clean_env(XDG_CACHE_HOME=str(cache))
    env.pop("CLRF_DEVICE", None)     # the device a clean cache picks
    work = tmp / "work"
    work.mkdir()
    first = subprocess.run([str(py.parent / "clrf"), "--quiet", "train", "--out", "run",
                            *SHORT_RUN], capture_output=True, text=True, cwd=work, env=env,
                           timeout=600)
    return SimpleNamespace(py=py, cache=cache, work=work, env=env, first=first)


@pytest.mark.slow
def test_the_wheel_in_a_fresh_venv_imports_and_runs_every_command(venv):
    py, env, work = venv.py, venv.env, venv.work
    r = subprocess.run([str(py), "-c", IMPORT_ALL], capture_output=True, text=True, cwd=work,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    clrf_bin = str(py.parent / "clrf")

    def run(*args, timeout=600):
        p = subprocess.run([clrf_bin, "--quiet", *args], capture_output=True, text=True,
                           cwd=work, env=env, timeout=timeout)
        assert p.returncode == 0, f"clrf {' '.join(args)}: {p.stderr[-3000:]}"
        return p

    assert venv.first.returncode == 0, f"clrf train: {venv.first.stderr[-3000:]}"
    v = run("--version")
    assert v.stdout.startswith(f"clrf {clrf.__version__}")
    if (ROOT / ".git").exists():     # the wheel was built from a checkout: it names the commit
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True).stdout.strip()
        assert f"(commit {head}" in v.stdout, v.stdout
    assert (work / "run" / "ckpt.npz").is_file() and (work / "run" / "metrics.csv").is_file()
    run("render", "--ckpt", "run", "--out", "frames", "--views", "orbit", "--frames", "2")
    assert list((work / "frames").glob("*.png"))
    run("eval", "--ckpt", "run", "--max-views", "2", "--lpips", "none", "--out", "eval.json")
    assert (work / "eval.json").is_file()
    run("export", "--ckpt", "run", "--points", "points.ply", "--n", "2000")
    assert (work / "points.ply").stat().st_size > 0


@pytest.mark.slow
def test_a_broken_install_is_an_install_error_and_a_reinstall_trains(venv, wheel, tmp_path):
    """012b9a6's failure: the self-check's `import clrf.references` failed in the install, the
    exception became a cached verdict on the driver, and clrf refused every device until the
    user found the cache. Now: an installation error naming the module and the fix, nothing
    cached, and the reinstalled clrf trains with the same cache on the device a clean cache
    picks (the shared venv's first run, from an empty cache, is that clean cache). The venv
    is whole again at the end."""
    py = venv.py
    site = Path(subprocess.run([str(py), "-c", "import clrf, os; print(os.path.dirname("
                                "clrf.__file__))"], capture_output=True, text=True,
                               env=_clean_env(), check=True).stdout.strip())
    shutil.rmtree(site / "references")
    # the clean run's probe figures and compiled kernels, without its verdicts
    cache = _cache_without_verdicts(tmp_path / "cache", venv.cache)
    env = _clean_env(XDG_CACHE_HOME=str(cache))
    env.pop("CLRF_DEVICE", None)
    work = tmp_path / "work"
    work.mkdir()
    clrf_bin = str(py.parent / "clrf")
    p = subprocess.run([clrf_bin, "--quiet", "train", "--out", "broken", *SHORT_RUN],
                       capture_output=True, text=True, cwd=work, env=env, timeout=600)
    assert p.returncode == 2, p.stderr[-3000:]
    assert "installed incompletely" in p.stderr and "clrf.references" in p.stderr, p.stderr
    assert "not the OpenCL driver's fault" in p.stderr
    assert "wrong gradients" not in p.stderr and "update the OpenCL driver" not in p.stderr
    verdicts = cache / "clrf" / "selfcheck.json"
    assert not verdicts.exists() or "references" not in verdicts.read_text()

    # the reinstall sees only the venv (not this environment's clrf, which it could uninstall)
    pth = site.parent / "outer_deps.pth"
    kept = pth.read_text()
    pth.unlink()
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q",
                        "--no-deps", "--force-reinstall", str(wheel)],
                       capture_output=True, text=True, env=_clean_env())
    pth.write_text(kept)
    assert r.returncode == 0, r.stderr[-3000:]
    p = subprocess.run([clrf_bin, "--quiet", "train", "--out", "fixed", *SHORT_RUN],
                       capture_output=True, text=True, cwd=work, env=env, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    trained_on = _device_of(p.stderr)
    # a clean cache trained too (the shared venv's first run), and accepts and refuses the
    # same devices as this one: the broken install left no verdict behind (which of two
    # devices within 10% of each other wins the timed race may differ between runs; the
    # verdicts may not)
    assert venv.first.returncode == 0, venv.first.stderr[-3000:]
    clean = dict(env, XDG_CACHE_HOME=str(venv.cache))

    def status(e):
        out = subprocess.run([clrf_bin, "devices"], capture_output=True, text=True, cwd=work,
                             env=e, timeout=600).stdout
        return {line.split()[0]: line.split()[-1] for line in out.splitlines()
                if re.match(r"\d+:\d+ ", line)}
    old_status, clean_status = status(env), status(clean)
    assert old_status == clean_status and old_status[trained_on] == "[ok]", (old_status,
                                                                            clean_status)


# sitecustomize.py for processes that run as if clrf/references/ were missing from the install:
# every import of it fails the way a missing package does (in the self-check's child too).
_WITHOUT_REFERENCES = """
import sys
class Missing:
    def find_spec(self, name, path=None, target=None):
        if name == "clrf.references" or name.startswith("clrf.references."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Missing())
"""


def _cache_without_verdicts(new: Path, old: Path | None = None) -> Path:
    """A cache folder with the device probe and compiled kernels of cache folder ``old``
    (default: this session's; a cold probe and build cost about 30 s on 2 vCPUs) but no
    self-check verdict, so that the check runs."""
    new.mkdir()
    old = old or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    (new / "clrf").mkdir()
    for name in ("devices.json", "workloads.json"):
        if (old / "clrf" / name).is_file():
            shutil.copy(old / "clrf" / name, new / "clrf" / name)
    for name in ("pocl", "pyopencl", "pytools"):
        if (old / name).is_dir():
            (new / name).symlink_to(old / name, target_is_directory=True)
    return new


@pytest.mark.slow
def test_the_command_line_reaches_the_self_check_without_the_references(tmp_path):
    """The fast guard of the broken-install test above (which builds a wheel and a venv:
    minutes, and marked slow): nothing `clrf train` imports before the device's self-check may
    import the float64 references, or a broken install is a traceback instead of the
    installation error. 28891e0 broke it: the splat config imported the twin's names."""
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(_WITHOUT_REFERENCES)
    path = os.pathsep.join(filter(None, [str(tmp_path / "site"), os.environ.get("PYTHONPATH")]))
    env = dict(os.environ, XDG_CACHE_HOME=str(_cache_without_verdicts(tmp_path / "cache")),
               PYTHONPATH=path)
    env.pop("CLRF_DEVICE", None)     # the self-check runs where clrf picks the device
    p = subprocess.run([sys.executable, "-m", "clrf.cli", "--quiet", "train", "--out",
                        str(tmp_path / "run"), *SHORT_RUN], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=600)
    assert p.returncode == 2, p.stderr[-3000:]
    assert "installed incompletely" in p.stderr and "clrf.references" in p.stderr, p.stderr
    assert not (tmp_path / "run" / "ckpt.npz").exists()


def _pip_pocl_specs() -> list:
    """``P:D`` of every device of pip's PoCL (pocl-binary-distribution, PoCL 3.0) here."""
    from clrf.runtime.device import list_devices
    return [f"{pi}:{di}" for pi, di, d in list_devices()
            if "pocl 3.0" in d.platform.version.lower()]


@pytest.mark.slow
def test_pips_pocl_trains_or_is_refused_never_a_crash(tmp_path):
    """pip's PoCL 3.0-rc2 is the only CPU driver `pip install "clrf[pocl]"` brings; it died
    with SIGSEGV on a Zen 4. Asked for by name it trains the procedural scene, or clrf
    refuses it with the reason (exit 2): the process never dies from a signal."""
    specs = _pip_pocl_specs()
    if not specs:
        pytest.skip("pip's PoCL (pocl-binary-distribution) is not installed here "
                    "(`bash tools/setup.sh` installs it)")
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache"))
    p = subprocess.run([sys.executable, "-m", "clrf.cli", "--quiet", "--device", specs[0],
                        "train", "--out", str(tmp_path / "run"), *SHORT_RUN],
                       capture_output=True, text=True, cwd=tmp_path, env=env, timeout=900)
    assert p.returncode >= 0, f"killed by signal {-p.returncode}: {p.stderr[-3000:]}"
    assert p.returncode in (0, 2), p.stderr[-3000:]
    if p.returncode == 2:
        assert "clrf: error: device" in p.stderr, p.stderr[-3000:]
    else:
        assert (tmp_path / "run" / "eval.json").is_file()


def test_version_names_the_commit_only_in_a_clrf_checkout(tmp_path):
    from clrf.runtime import version
    assert version.git_commit(tmp_path) is None              # no repository
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    assert version.git_commit(tmp_path) is None              # a repository, not clrf's
    text = version.describe()
    assert text.startswith(f"clrf {clrf.__version__}")
