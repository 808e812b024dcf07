"""Split an OpenCL compiler's build log into diagnostics and progress chatter.

``clGetProgramBuildInfo(CL_PROGRAM_BUILD_LOG)`` is free text. Besides the compiler's warnings
and errors, some implementations write progress lines into every log, e.g. Intel's oneAPI CPU
runtime::

    Compilation started
    1:12:13: warning: implicit conversion from 'float' to 'int' changes value from 2.5 to 2
       12 |     int k = 2.5f;
          |         ~   ^~~~
    Compilation done
    Linking started
    ...
    Done.

``split_log`` returns the diagnostics (the warning above with its excerpt lines) and the
chatter (every other line). Diagnostic headers are recognised in the two shapes the
implementations write:

- clang's ``<file>:<line>:<col>: <severity>: <message>`` (Oclgrind and rusticl write
  ``input.cl``, Intel the program's number, clang itself ``<stdin>`` or ``<source>``);
- PoCL's ``<severity>: <file>:<line>:<col>: <message>``;

and ``<severity>: <message>`` without a location. A ``note`` belongs to the diagnostic before
it; ``In file included from`` lines belong to the diagnostic after them; any other line after a
diagnostic is its source excerpt (caret, fix-it). The split is conservative: a line that is
neither a known chatter pattern (``CHATTER``, with the implementation that writes it) nor part
of a diagnostic becomes a diagnostic of severity ``"unknown"``, so a format not seen before is
shown, never hidden. Real logs of each implementation are kept in tests/fixtures/build_logs/.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

# (pattern, who writes it). Each pattern matches a whole line, leading/trailing blanks aside.
CHATTER = (
    # Intel oneAPI OpenCL CPU runtime (2026.22): progress of its front end, linker and backend.
    (r"Compilation (started|done|failed)", "Intel oneAPI CPU"),
    (r"Linking (started|done|failed)", "Intel oneAPI CPU"),
    (r"Device build (started|done|failed)", "Intel oneAPI CPU"),
    (r"Options used by backend compiler:.*", "Intel oneAPI CPU"),
    # its backend's optimisation remarks, all at <unknown>:0:0 ("loop not vectorized: ...",
    # "Kernel was 16-way vectorized", "11398 instructions in function")
    (r"remark: <unknown>:0:0: .*", "Intel oneAPI CPU"),
    (r'Kernel "?\w+"? was (successfully vectorized( \(\d+\))?|not vectorized)', "Intel oneAPI CPU"),
    (r"Reload Program Binary Object\.", "Intel oneAPI CPU"),   # a program from its binary
    (r"Done\.", "Intel oneAPI CPU"),
    # PoCL 3.x: closes the log of a failed build (the errors come before it).
    (r"Device .* failed to build the program", "PoCL"),
    # Mesa rusticl 22.3 (clc): closes the log of a failed build.
    (r"Error executing LLVM compilation action\.", "Mesa rusticl"),
    # NVIDIA's OpenCL (CUDA 13.0, driver 580): one line per kernel of every program, its own
    # code or not (the kernel attribute wins over noinline), in every log.
    (r"\(\): Warning: Function \w+ is a kernel, so overriding noinline attribute\. "
     r"The function may be inlined when called\.", "NVIDIA"),
    # clang (every clang-based compiler): the count after the diagnostics themselves.
    (r"\d+ (warnings?|errors?)( and \d+ (warnings?|errors?))? generated\.", "clang"),
)
_CHATTER = [re.compile(p) for p, _ in CHATTER]

_SEV = r"(?P<sev>fatal error|error|warning|note|remark)"
_LOC = r"(?P<file>\S.*?):(?P<line>\d+):(?:(?P<col>\d+):)?"
_HEADERS = [
    re.compile(rf"{_LOC} {_SEV}: (?P<msg>.*)"),    # clang
    re.compile(rf"{_SEV}: {_LOC} (?P<msg>.*)"),    # PoCL
    re.compile(rf"{_SEV}: (?P<msg>.*)"),           # no location
]
_INCLUDED = re.compile(r"(In file included from|\s+from) \S.*:\d+[:,]")


@dataclass
class Diagnostic:
    """One compiler message: severity ("error", "fatal error", "warning", "remark", "note" for
    a note without a parent, "unknown" for an unrecognised line), its location when the
    compiler gave one, the message, the notes attached to it, and every log line it spans
    (include context, header, source excerpt, notes) in ``lines``."""

    severity: str
    message: str
    file: str | None = None
    line: int | None = None
    col: int | None = None
    notes: list = field(default_factory=list)
    lines: list = field(default_factory=list)

    @property
    def location(self) -> str:
        """``file:line:col`` (as much as the compiler gave), or ``""``."""
        if self.file is None:
            return ""
        return ":".join(str(x) for x in (self.file, self.line, self.col) if x is not None)

    @property
    def text(self) -> str:
        return "\n".join(self.lines)


@dataclass
class SplitLog:
    diagnostics: list    # [Diagnostic]
    chatter: list        # [str] lines matched by CHATTER


def _header(line: str) -> Diagnostic | None:
    for pat in _HEADERS:
        m = pat.fullmatch(line)
        if m:
            g = m.groupdict()
            return Diagnostic(
                severity=g["sev"], message=g["msg"], file=g.get("file"),
                line=int(g["line"]) if g.get("line") else None,
                col=int(g["col"]) if g.get("col") else None, lines=[line])
    return None


def is_chatter(line: str) -> bool:
    s = line.strip()
    return any(p.fullmatch(s) for p in _CHATTER)


def split_log(log: str) -> SplitLog:
    """The diagnostics and the chatter of a build log (see the module doc). Blank lines are
    dropped. ``split_log("Compilation started\\nin.cl:3:9: warning: x\\nDone.")`` gives one
    warning at ``in.cl:3:9`` and the two chatter lines."""
    diags, chatter, context = [], [], []
    current = None          # the diagnostic that excerpt and note lines attach to
    for line in log.splitlines():
        if not line.strip():
            continue
        if is_chatter(line):
            chatter.append(line.strip())
            current = None
            continue
        if _INCLUDED.match(line):
            context.append(line)
            current = None
            continue
        d = _header(line.strip())
        if d is not None and d.severity == "note" and current is not None and not context:
            current.notes.append(d)
            current.lines.append(line)
            continue
        if d is None and current is not None and not context:
            current.lines.append(line)          # source excerpt, caret or fix-it
            continue
        if d is None:           # each unrecognised line stands alone
            d = Diagnostic("unknown", line.strip(), lines=[line])
        d.lines[:0] = context
        context = []
        diags.append(d)
        current = d if d.severity != "unknown" else None
    for line in context:        # include context with no diagnostic after it: show it
        diags.append(Diagnostic("unknown", line.strip(), lines=[line]))
    return SplitLog(diags, chatter)


def diagnostics(log: str) -> list:
    """``split_log(log).diagnostics``: what a user should see of a build log."""
    return split_log(log).diagnostics
