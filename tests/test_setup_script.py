"""tools/setup.sh decides when to install the distribution's PoCL: run it in a sandbox.

The sandbox's PATH holds only stubs: a fake ``python`` (makes the venv, accepts ``pip install``
and answers ``clrf devices --check`` with the exit status the scenario sets, before and after
the install), a fake ``apt-get`` that records what it was asked, and fake ``id``/``sudo``.
"""
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TOOLS = ("env", "rm", "dirname", "mkdir", "cp", "cat", "touch", "true", "mktemp")

FAKE_PYTHON = """#!/bin/bash
case "$1" in
  -c)   # the source stamp (FAKE_STAMP; none: the stamp fails) or an import check (fails)
    if [[ "$2" == *hashlib* ]] && [ -n "$FAKE_STAMP" ]; then echo "$FAKE_STAMP"; exit 0; fi
    exit 1 ;;
esac
case "$1 $2" in
  "-m venv") mkdir -p "$3/bin" && cp "$0" "$3/bin/python" && echo "$3" >> "$FAKE_STATE/venv" ;;
  "-m pip") echo "${*:3}" >> "$FAKE_STATE/pip" ;;
  "-m clrf.cli")
    echo "$*" >> "$FAKE_STATE/checks"
    if [ -e "$FAKE_STATE/intel" ]; then exit "${FAKE_INTEL:-$FAKE_BEFORE}"; fi
    if [ -e "$FAKE_STATE/installed" ]; then exit "$FAKE_AFTER"; else exit "$FAKE_BEFORE"; fi ;;
  "-m clrf.runtime.icd") touch "$FAKE_STATE/intel" ;;
  *) exit 99 ;;
esac
"""
FAKE_APT = """#!/bin/bash
echo "$*" >> "$FAKE_STATE/apt"
[ -n "$FAKE_APT_FAIL" ] && exit 100
case "$*" in
  *install*) touch "$FAKE_STATE/installed" ;;
  "download libclc-19") touch "libclc-19_1%3a19.1.7_all.deb" ;;   # into the current folder
esac
"""
FAKE_DPKG_DEB = """#!/bin/bash
echo "$*" >> "$FAKE_STATE/dpkg-deb"
[ "$1" = "-x" ] && [ -e "$2" ] || exit 2
mkdir -p "$3/usr/lib/clc" && touch "$3/usr/lib/clc/gfx1100-amdgcn-mesa-mesa3d.bc"
"""
FAKE_ID = '#!/bin/bash\necho "$FAKE_UID"\n'
FAKE_SUDO = """#!/bin/bash
[ "$1" = "-n" ] || exit 97          # setup.sh must never let sudo prompt
shift
[ -n "$FAKE_SUDO_OK" ] || exit 1
exec "$@"
"""


def _script(path: Path, text: str):
    path.write_text(text)
    path.chmod(0o755)


def run_setup(tmp_path, before, after=0, uid=0, apt=True, sudo_ok=True, apt_fail=False,
              extras="test", mpi_tools=False, browser=False, intel=None, gpucc_tools=False,
              stamp=None, args=()):
    """Run setup.sh in the sandbox under ``tmp_path`` (again in the same one when it is there:
    its repo, with the venv the last run left, and its logs)."""
    repo, stubs, state = tmp_path / "repo", tmp_path / "bin", tmp_path / "state"
    for p in (repo / "tools", stubs, state):
        p.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "tools" / "setup.sh", repo / "tools" / "setup.sh")
    for tool in TOOLS:
        if not (stubs / tool).exists():
            os.symlink(shutil.which(tool), stubs / tool)
    _script(stubs / "python", FAKE_PYTHON)
    _script(stubs / "id", FAKE_ID)
    _script(stubs / "sudo", FAKE_SUDO)
    if apt:
        _script(stubs / "apt-get", FAKE_APT)
    if mpi_tools:                       # an MPI library already installed
        for tool in ("mpicc", "mpirun"):
            _script(stubs / tool, "#!/bin/bash\n")
    _script(stubs / "dpkg-deb", FAKE_DPKG_DEB)
    if gpucc_tools:                     # clang-19 and ocloc already installed
        for tool in ("clang-19", "ocloc"):
            _script(stubs / tool, "#!/bin/bash\n")
    if browser:                         # Chromium and its driver already installed
        for tool in ("chromium", "chromedriver"):
            _script(stubs / tool, "#!/bin/bash\n")
    env = {"PATH": str(stubs), "PYTHON": "python", "FAKE_STATE": str(state),
           "FAKE_BEFORE": str(before), "FAKE_AFTER": str(after), "FAKE_UID": str(uid),
           "FAKE_SUDO_OK": "1" if sudo_ok else "", "FAKE_APT_FAIL": "1" if apt_fail else "",
           "CLRF_DEVICE": "1:0"}
    if intel is not None:             # what the check answers once Intel's runtime is in
        env["FAKE_INTEL"] = str(intel)
    if stamp is not None:             # the source stamp the standard-library hash gives
        env["FAKE_STAMP"] = stamp
    r = subprocess.run([shutil.which("bash"), str(repo / "tools" / "setup.sh"), *args, extras],
                       env=env, capture_output=True, text=True, timeout=60)
    apt_log = (state / "apt").read_text() if (state / "apt").exists() else ""
    checks = (state / "checks").read_text().splitlines() if (state / "checks").exists() else []
    return r, apt_log, checks


@pytest.mark.parametrize("before, after, uid, apt, sudo_ok, apt_fail, rc, installs, says", [
    (0, 0, 0, True, True, False, 0, False, ""),                     # pip's PoCL is fine
    (3, 0, 0, True, True, False, 0, True, "slow driver"),          # generic target: install
    (1, 0, 0, True, True, False, 0, True, "no working"),           # nothing works: install
    (3, 3, 0, True, True, False, 0, True, "slow driver"),          # still slow: keep going
    (1, 1, 0, True, True, False, 1, True, "no working"),           # still nothing: fail
    (3, 0, 1000, True, True, False, 0, True, "slow driver"),       # sudo -n works
    (1, 0, 1000, True, False, False, 1, False, "sudo needs a password"),
    (3, 0, 1000, True, False, False, 0, False, "sudo needs a password"),
    (3, 0, 0, False, True, False, 0, False, "no apt-get"),
    (1, 0, 0, False, True, False, 1, False, "no apt-get"),
    (1, 0, 0, True, True, True, 1, False, "apt-get install pocl-opencl-icd failed"),
])
def test_setup_installs_distribution_pocl_when_needed(tmp_path, before, after, uid, apt, sudo_ok,
                                                      apt_fail, rc, installs, says):
    r, apt_log, checks = run_setup(tmp_path, before, after, uid, apt, sudo_ok, apt_fail)
    assert r.returncode == rc, r.stderr
    assert ("install -y -qq pocl-opencl-icd" in apt_log) == installs
    assert bool(apt_log) == (installs or apt_fail)  # apt-get is never run when not needed
    assert says in r.stderr
    # probed again after an install, and once more after trying Intel's runtime from PyPI
    # when no fast driver came of it (the fake runtime changes nothing here)
    intel_tried = (after if installs else before) != 0
    assert len(checks) == 1 + installs + intel_tried
    assert ("Intel's CPU runtime" in r.stderr) == intel_tried
    assert all(c == "-m clrf.cli devices --check" for c in checks)


@pytest.mark.parametrize("before, intel, rc", [(3, 0, 0), (1, 0, 0), (1, 1, 1), (3, 3, 0)])
def test_setup_tries_intels_runtime_without_the_distributions_pocl(tmp_path, before, intel, rc):
    """No apt-get (or no root): pip's PoCL is slow or broken, so Intel's CPU runtime comes
    from PyPI; clrf then picks whichever measures faster."""
    r, apt_log, checks = run_setup(tmp_path, before, apt=False, intel=intel)
    assert r.returncode == rc, r.stderr
    assert "trying Intel's CPU runtime" in r.stderr
    pip_log = (tmp_path / "state" / "pip").read_text()
    assert ".[pocl,intel]" in pip_log
    assert len(checks) == 2


@pytest.mark.parametrize("mpi_tools, uid, sudo_ok, apt_fail, rc, installs, says", [
    (False, 0, True, False, 0, True, "installing Open MPI"),      # root: apt-get installs it
    (False, 1000, True, False, 0, True, "installing Open MPI"),   # sudo -n works
    (True, 0, True, False, 0, False, ""),                         # mpicc and mpirun exist
    (False, 1000, False, False, 1, False, "sudo apt-get install openmpi-bin libopenmpi-dev"),
    (False, 0, True, True, 1, False, "apt-get install openmpi-bin libopenmpi-dev failed"),
])
def test_setup_installs_open_mpi_for_the_mpi_extra(tmp_path, mpi_tools, uid, sudo_ok, apt_fail,
                                                   rc, installs, says):
    r, apt_log, _ = run_setup(tmp_path, 0, uid=uid, sudo_ok=sudo_ok, apt_fail=apt_fail,
                              extras="test,mpi", mpi_tools=mpi_tools)
    assert r.returncode == rc, r.stderr
    assert ("install -y -qq openmpi-bin libopenmpi-dev" in apt_log) == installs
    assert says in r.stderr
    assert "pocl-opencl-icd" not in apt_log


def test_setup_without_the_mpi_extra_installs_no_mpi(tmp_path):
    r, apt_log, _ = run_setup(tmp_path, 0, extras="test")
    assert r.returncode == 0 and apt_log == ""


@pytest.mark.parametrize("extras, browser, sudo_ok, rc, installs", [
    ("view,test", False, True, 0, True),     # the browser test needs Chromium: install it
    ("test,view", False, True, 0, True),
    ("view,test", True, True, 0, False),     # already there
    ("view", False, True, 0, False),         # the viewer alone needs no browser
    ("test", False, True, 0, False),
    ("view,test", False, False, 1, False),   # cannot install: say so and fail
    ("web,test", False, True, 0, True),      # the exported page's browser test too
    ("web", False, True, 0, False),
])
def test_setup_installs_chromium_for_view_and_test(tmp_path, extras, browser, sudo_ok, rc,
                                                   installs):
    r, apt_log, _ = run_setup(tmp_path, 0, uid=0 if sudo_ok else 1000, sudo_ok=sudo_ok,
                              extras=extras, browser=browser)
    assert r.returncode == rc, r.stderr
    assert ("install -y -qq chromium chromium-driver" in apt_log) == installs
    assert ("headless Chromium" in r.stderr) == (installs or rc == 1)
def test_setup_installs_the_eval_extra_without_torchvision(tmp_path):
    r, _, _ = run_setup(tmp_path, 0, extras="test,eval")
    assert r.returncode == 0, r.stderr
    pip = (tmp_path / "state" / "pip").read_text().splitlines()
    assert "install -q .[pocl,test]" in pip, pip             # eval is not a pip extra here
    # gsplat's exporter (the splat files' tests) without its CUDA build's dependencies
    assert pip[-3:] == ["install -q torch==2.13.0", "install -q --no-deps lpips==0.1.4",
                        "install -q --no-deps gsplat==1.5.3"], pip
    r, _, _ = run_setup(tmp_path / "b", 0, extras="test")
    assert not any("lpips" in line or "gsplat" in line
                   for line in (tmp_path / "b" / "state" / "pip").read_text().splitlines())


def test_setup_gpucc_installs_the_offline_compilers_once(tmp_path):
    """Extra gpucc: clang-19 and ocloc from apt, libclc-19's bitcode downloaded and unpacked
    into .gpucc/ (never installed: it would remove mesa-opencl-icd); not a pip extra. A second
    run with everything in place asks apt for nothing."""
    r, apt_log, _ = run_setup(tmp_path, 0, extras="test,gpucc")
    assert r.returncode == 0, r.stderr
    assert "install -y -qq clang-19 intel-opencl-icd" in apt_log
    assert "download libclc-19" in apt_log and "install -y -qq libclc" not in apt_log
    repo = tmp_path / "repo"
    assert (repo / ".gpucc/libclc/usr/lib/clc/gfx1100-amdgcn-mesa-mesa3d.bc").exists()
    pip = (tmp_path / "state" / "pip").read_text().splitlines()
    assert "install -q .[pocl,test]" in pip, pip
    # again, with the compilers on PATH and the bitcode unpacked: nothing to do
    bc = tmp_path / "b" / "repo" / ".gpucc/libclc/usr/lib/clc/gfx1100-amdgcn-mesa-mesa3d.bc"
    bc.parent.mkdir(parents=True)
    bc.touch()
    r, apt_log, _ = run_setup(tmp_path / "b", 0, extras="gpucc", gpucc_tools=True)
    assert r.returncode == 0, r.stderr
    assert apt_log == ""


def test_setup_adds_extras_to_the_venv_and_installs_nothing_twice(tmp_path):
    """Extras add up in one venv; the same call again (same extras, same source stamp) runs
    no pip; --fresh makes a new venv with exactly the extras asked for."""
    def pip_lines():
        f = tmp_path / "state" / "pip"
        return f.read_text().splitlines() if f.exists() else []

    def venvs():
        return (tmp_path / "state" / "venv").read_text().count("\n")

    record = tmp_path / "repo" / ".venv" / "clrf-setup.txt"
    r, _, _ = run_setup(tmp_path, 0, extras="test", stamp="s1")
    assert r.returncode == 0, r.stderr
    assert pip_lines()[-1] == "install -q .[pocl,test]" and venvs() == 1
    assert record.read_text() == "test\ns1\n"
    r, _, _ = run_setup(tmp_path, 0, extras="view", stamp="s2")
    assert r.returncode == 0, r.stderr
    assert pip_lines()[-1] == "install -q .[pocl,test,view]", pip_lines()   # both extras
    assert venvs() == 1 and record.read_text() == "test,view\ns2\n"
    n = len(pip_lines())
    r, _, checks = run_setup(tmp_path, 0, extras="view", stamp="s2")
    assert r.returncode == 0, r.stderr
    assert len(pip_lines()) == n and "nothing to install" in r.stderr     # nothing installed
    assert checks[-1] == "-m clrf.cli devices --check"                     # still checked
    r, _, _ = run_setup(tmp_path, 0, extras="view", stamp="s3")            # the source changed
    assert len(pip_lines()) == n + 1 and pip_lines()[-1] == "install -q .[pocl,test,view]"
    r, _, _ = run_setup(tmp_path, 0, extras="view", stamp="s4", args=("--fresh",))
    assert r.returncode == 0, r.stderr
    assert venvs() == 2 and pip_lines()[-1] == "install -q .[pocl,view]"
    assert record.read_text() == "view\ns4\n"
    # no stamp (the hash failed): always installs, records nothing
    r, _, _ = run_setup(tmp_path, 0, extras="view", stamp="")
    assert pip_lines()[-1] == "install -q .[pocl,view]" and not record.exists()
