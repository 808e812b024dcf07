"""clrf's version (``VERSION``, which ``clrf.__version__`` and setup.cfg read), and the commit
it was built from where that is known.

``describe()`` gives ``clrf 0.1.0 (commit 012b9a6)``: the commit is read from git when clrf
runs from a git checkout, else from ``_build_commit.py``, which the wheel build writes
(setup.py) when it builds from a checkout; ``+modified`` marks uncommitted changes.
"""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

VERSION = "0.1.0"


def git_commit(folder: Path) -> str | None:
    """``012b9a6`` (``+modified`` with uncommitted changes) of the git checkout that holds
    ``folder``, or None where there is none (or no git)."""
    try:
        top = subprocess.run(["git", "-C", str(folder), "rev-parse", "--show-toplevel"],
                             capture_output=True, text=True, timeout=10)
        if top.returncode != 0:
            return None
        if not (Path(top.stdout.strip()) / "clrf" / "__init__.py").is_file():
            return None   # a git repository around an install, not a clrf checkout
        head = subprocess.run(["git", "-C", str(folder), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(folder), "status", "--porcelain",
                                "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("+modified" if dirty.stdout.strip() else "")


def commit() -> str | None:
    """The commit this clrf runs from (a checkout) or was built from (a wheel), or None."""
    here = Path(__file__).resolve().parent.parent      # the clrf package (this is clrf/runtime)
    found = git_commit(here)
    if found:
        return found
    try:   # read, not imported: the file exists only in a built wheel
        text = (here / "_build_commit.py").read_text()
    except OSError:
        return None
    m = re.search(r"^COMMIT = '([^']*)'", text, flags=re.M)
    return (m.group(1) or None) if m else None


def describe() -> str:
    c = commit()
    return f"clrf {VERSION}" + (f" (commit {c})" if c else "")
