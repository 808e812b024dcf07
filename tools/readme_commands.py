"""Print the README's commands for a fresh machine, as written (what .ci/run runs).

    python3 tools/readme_commands.py 1     # install, then train the built-in scene
    python3 tools/readme_commands.py 2     # install with the test dependencies, then test

They are the shell blocks of README.md's section "Two commands on a fresh machine", in order;
standard library only, so it runs before anything is installed.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"
SECTION = "## Two commands on a fresh machine"


def commands(text: str) -> list:
    """The one-line shell blocks of SECTION, in order."""
    if SECTION not in text:
        raise SystemExit(f"{README}: no section '{SECTION}'")
    body = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^```(?:sh|bash)\n(.*?)^```", body, flags=re.S | re.M)
    out = []
    for block in blocks:
        lines = [x for x in block.splitlines() if x.strip() and not x.lstrip().startswith("#")]
        if len(lines) != 1:
            raise SystemExit(f"{README}: a block of '{SECTION}' holds {len(lines)} lines; "
                             f"each must be one command")
        out.append(lines[0].strip())
    return out


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cmds = commands(README.read_text())
    if len(cmds) != 2:
        raise SystemExit(f"{README}: '{SECTION}' gives {len(cmds)} commands, not two")
    if len(argv) != 1 or argv[0] not in ("1", "2"):
        raise SystemExit("usage: python3 tools/readme_commands.py 1|2")
    print(cmds[int(argv[0]) - 1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
