"""Package discovery and the build's commit (the rest of the metadata is in setup.cfg).

Every package under clrf/ is found, none listed by hand, so a new one cannot be left out of
the wheel; the kernel sources of cl/ travel as the data package clrf.cl (setup.cfg maps it).
A folder of clrf/ holding Python files without an __init__.py would not be found: the
install test (tests/test_install.py) fails on such a folder. A build from a git checkout
writes the commit into clrf/_build_commit.py of the build (``clrf --version`` prints it).
"""
import subprocess
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py


def _commit():
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(here), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    if head.returncode != 0:
        return ""
    return head.stdout.strip() + ("+modified" if dirty.stdout.strip() else "")


class BuildWithCommit(build_py):
    def run(self):
        super().run()
        if not self.dry_run:
            out = Path(self.build_lib) / "clrf" / "_build_commit.py"
            out.write_text(f'"""Written by setup.py at build time."""\nCOMMIT = {_commit()!r}\n')


setup(packages=find_packages(include=["clrf", "clrf.*"]) + ["clrf.cl"],
      cmdclass={"build_py": BuildWithCommit})
