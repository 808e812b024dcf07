"""The README's commands and every documentation link stay correct.

- Every line of a ```sh / ```bash block in README.md is split like a shell would (quotes,
  backslash continuations, `&&`, `;`, `|`, leading VAR=value assignments, comments) and each
  command in it is checked without running it:
    * `clrf ...` (also `.venv/bin/clrf`): its arguments parse with clrf.cli.main.build_parser(),
      and for `clrf train` the --set / --SECTION.KEY values pass clrf.training.config.build_config;
    * `python -m MODULE` names an importable module, `python tools/X.py` an existing file;
    * `bash tools/setup.sh EXTRAS`: each extra is in setup.cfg's extras_require or handled by
      tools/setup.sh itself (a `*,NAME,*` case);
    * `mpirun ... CMD` and `sh -c 'CMD'` check CMD; a few outside programs (colmap, mkdir)
      are allowed by name, any other program fails the test.
- Every `clrf.NAME` used in a ```python block of README.md exists.
- Every relative link (`[text](path)`, `![alt](path)`, `<img src="path">`) in README.md and
  docs/*.md points at an existing file (anchors are checked in the files of this repo).
- README.md is at most 320 lines.
"""
from __future__ import annotations

import configparser
import contextlib
import importlib.util
import io
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_README_LINES = 320
OUTSIDE_PROGRAMS = {"colmap", "mkdir", "ssh", "cd"}
SHELL_LANGS = {"sh", "bash", "shell", "console"}


def fenced_blocks(text):
    """[(language, [lines])] of the ``` fenced blocks of a Markdown text."""
    blocks, lang, lines = [], None, None
    for line in text.splitlines():
        m = re.match(r"^\s*```\s*([\w+-]*)", line)
        if m and lines is None:
            lang, lines = m.group(1).lower(), []
        elif m:
            blocks.append((lang, lines))
            lang, lines = None, None
        elif lines is not None:
            lines.append(line)
    assert lines is None, "unclosed ``` block"
    return blocks


def shell_commands(lines):
    """Commands (token lists) of shell lines: continuations joined, comments dropped, split at
    && ; | and with leading VAR=value assignments removed."""
    joined, buf = [], ""
    for line in lines:
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1] + " "
            continue
        joined.append(buf + line)
        buf = ""
    if buf:
        joined.append(buf)
    cmds = []
    for line in joined:
        lex = shlex.shlex(line, posix=True, punctuation_chars="&|;")
        lex.whitespace_split = True
        lex.commenters = "#"
        cmd = []
        for tok in list(lex) + [";"]:
            if tok in ("&&", "||", ";", "|", "&"):
                while cmd and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", cmd[0]):
                    cmd.pop(0)
                if cmd:
                    cmds.append(cmd)
                cmd = []
            else:
                cmd.append(tok)
    return cmds


def setup_extras():
    """Extras `bash tools/setup.sh` accepts: setup.cfg's extras_require plus the ones the
    script handles itself."""
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    names = set(cfg["options.extras_require"].keys())
    names |= set(re.findall(r"\*,(\w+),\*\)", (ROOT / "tools" / "setup.sh").read_text()))
    return names


def check_clrf(args, relaxed=False):
    """``args`` parse with clrf's parser (``relaxed``: no argument is required), and a
    `train`'s configuration values build; `--help` / `--version` count as parsing."""
    from clrf.cli.main import build_parser, parse_set
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            parser = build_parser()
            a = (_relaxed(parser) if relaxed else parser).parse_args(args)
    except SystemExit as e:
        if e.code == 0:
            return
        raise AssertionError(f"`clrf {' '.join(args)}` does not parse: {err.getvalue().strip()}"
                             ) from e
    if a.cmd == "train":   # the configuration values too (keys, types, ranges)
        from clrf.cli.config_flags import config_flags, merge_overrides
        from clrf.training.config import ConfigError, build_config
        try:
            build_config(a.preset or "", None, merge_overrides(parse_set(a.set), config_flags(a)))
        except ConfigError as e:
            raise AssertionError(f"`clrf {' '.join(args)}`: {e}") from e


def check_python(args, what):
    if args[:1] == ["-m"]:
        assert len(args) >= 2, f"{what}: -m without a module"
        assert importlib.util.find_spec(args[1]) is not None, f"{what}: no module {args[1]}"
    else:
        script = next((a for a in args if not a.startswith("-")), None)
        assert script is not None, f"{what}: no script"
        assert (ROOT / script).is_file(), f"{what}: {script} does not exist"


def check_command(cmd, extras):
    what = "`" + " ".join(cmd) + "`"
    while cmd and cmd[0] in ("exec", "nice", "env"):
        cmd = cmd[1:]
    prog, args = Path(cmd[0]).name, cmd[1:]
    if prog == "clrf":
        check_clrf(args)
    elif prog == "pytest":      # the venv's test runner: its options are pytest's
        assert cmd[0] in (".venv/bin/pytest", "pytest"), f"{what}: run the venv's pytest"
    elif re.fullmatch(r"python(3(\.\d+)?)?", prog):
        check_python(args, what)
    elif prog == "bash" and args[:1] == ["tools/setup.sh"]:
        for extra in (args[1].split(",") if len(args) > 1 else []):
            assert extra in extras, f"{what}: extra {extra!r} is neither in setup.cfg nor " \
                                    f"handled by tools/setup.sh ({sorted(extras)})"
    elif prog == "mpirun":
        i = 0
        with_value = {"-n", "-np", "--bind-to", "--map-by", "-x", "--host", "-H"}
        while i < len(args) and args[i].startswith("-"):
            i += 2 if args[i] in with_value else 1
        assert i < len(args), f"{what}: mpirun without a program"
        check_command(args[i:], extras)
    elif prog == "sh" and args[:1] == ["-c"]:
        for sub in shell_commands([args[1]]):
            check_command(sub, extras)
    else:
        assert prog in OUTSIDE_PROGRAMS, f"{what}: unknown program {prog!r} in a README " \
                                         f"command block (add it to OUTSIDE_PROGRAMS if meant)"


def readme_shell_commands():
    out = []
    for lang, lines in fenced_blocks(README.read_text()):
        if lang in SHELL_LANGS:
            out += shell_commands(lines)
    return out


def doc_files():
    return [README] + sorted((ROOT / "docs").glob("*.md"))


_OPTIONAL = re.compile(r"\[(--?[^\[\]]*)\]")    # a synopsis's [--flag VALUE]


def inline_clrf_commands(text):
    """`clrf ...` commands written inline (one backtick span each) in Markdown prose, as token
    lists: a usage synopsis's ``[optional]`` brackets dropped, ``...`` dropped, and ``a|b``
    alternatives of one token expanded into one command each."""
    out = []
    for span in re.findall(r"`((?:\.venv/bin/)?clrf [^`\n]+)`", _strip_fenced(text)):
        try:
            toks = shlex.split(_OPTIONAL.sub(r" \1 ", span), comments=True)
        except ValueError:
            toks = span.split()
        alts = [[]]
        for tok in toks:
            if tok in ("...", "\u2026"):
                continue
            choices = tok.split("|") if "|" in tok else [tok]
            alts = [a + [c] for a in alts for c in choices]
        out += alts
    return out


def _strip_fenced(text):
    return re.sub(r"^\s*```.*?^\s*```", "", text, flags=re.S | re.M)


def docs_commands():
    """(file, command, inline) of every shell block line and inline `clrf ...` span of
    README.md and docs/*.md."""
    out = []
    for doc in doc_files():
        text = doc.read_text()
        for lang, lines in fenced_blocks(text):
            if lang in SHELL_LANGS:
                # a usage synopsis line (`clrf eval --ckpt DIR [--data PATH]`) is checked as
                # prose is; every other line as a command to run
                synopsis = [x for x in lines if re.match(r"\s*clrf .*\[", x)]
                out += [(doc, c, False) for c in shell_commands(
                    [x for x in lines if x not in synopsis])]
                out += [(doc, c, True) for x in synopsis
                        for c in inline_clrf_commands(f"`{x.split('#')[0].strip()}`")]
        out += [(doc, c, True) for c in inline_clrf_commands(text)]
    return out


def _number_or_placeholder(kind):
    def parse(text):
        return text if re.fullmatch(r"[A-Z][A-Z0-9_]*", text) else kind(text)
    return parse


def _relaxed(parser):
    """``parser`` with no argument required, its subcommands' too: prose names a command
    without the arguments a run needs (`clrf eval` reads a checkpoint)."""
    for act in parser._actions:
        act.required = False
        if act.type in (int, float):   # a synopsis's placeholder value (`--port N`)
            act.type = _number_or_placeholder(act.type)
        if isinstance(act.choices, dict):      # the subcommands
            for sub in act.choices.values():
                _relaxed(sub)
    return parser


@pytest.mark.parametrize("where,cmd,inline", [(d.relative_to(ROOT).as_posix(), c, i)
                                              for d, c, i in docs_commands()
                                              if Path(c[0]).name == "clrf"],
                         ids=lambda x: x if isinstance(x, str) else
                         " ".join(x)[:50] if isinstance(x, list) else str(x))
def test_every_clrf_command_in_the_docs_parses(where, cmd, inline):
    """Every `clrf ...` of README.md and docs/*.md, in a shell block (as written: required
    arguments too) or inline in prose (a command named without all its arguments), parses with
    the real parser: unknown commands, flags, choices and configuration keys fail. An upper
    case word where the command goes (`clrf COMMAND --help`) is a placeholder."""
    args = cmd[1:]
    if inline and args and re.fullmatch(r"[A-Z_]+", args[0]):
        return
    try:
        check_clrf(args, relaxed=inline)
    except AssertionError as e:
        raise AssertionError(f"{where}: {e}") from None


def test_inline_checker_rejects_wrong_commands():
    text = "use `clrf train --model grid|voxels`, `clrf evaluate` or `clrf eval --no-such`"
    cmds = inline_clrf_commands(text)
    assert ["clrf", "train", "--model", "grid"] in cmds
    bad = [c for c in cmds if c != ["clrf", "train", "--model", "grid"]]
    assert len(bad) == 3
    for c in bad:
        with pytest.raises(AssertionError):
            check_clrf(c[1:], relaxed=True)
    check_clrf(["eval"], relaxed=True)
    with pytest.raises(AssertionError):
        check_clrf(["eval"])


def test_readme_names_every_representation_and_section():
    from clrf import registry
    from clrf.cli.config_flags import sections
    text = README.read_text()
    for name in registry.names():
        assert f"--model {name}" in text, f"README.md never shows `--model {name}`"
    for name, _, _ in sections():
        assert f"`{name}`" in text, f"README.md never names the configuration section `{name}`"


def test_readme_has_command_blocks():
    cmds = readme_shell_commands()
    progs = {Path(c[0]).name for c in cmds}
    assert "clrf" in progs and "bash" in progs, progs
    assert len(cmds) >= 10


@pytest.mark.parametrize("cmd", readme_shell_commands(), ids=lambda c: " ".join(c)[:60])
def test_readme_command(cmd):
    check_command(cmd, setup_extras())


def test_checker_rejects_wrong_commands():
    """The checks can fail: a wrong option, module, script, extra and program are caught."""
    extras = setup_extras()
    for bad in (["clrf", "train", "--no-such-option"], ["clrf", "render", "--views", "sideways",
                                                         "--ckpt", "x", "--out", "y"],
                ["python", "-m", "clrf.no_such_module"], ["python", "tools/no_such_tool.py"],
                ["bash", "tools/setup.sh", "test,no_such_extra"], ["frobnicate", "--now"],
                ["clrf", "train", "--set", "grid.no_such_key=1"],
                ["clrf", "train", "--grid.sh_degree", "9"]):
        with pytest.raises(AssertionError):
            check_command(bad, extras)
    check_command(["bash", "tools/setup.sh", "test,mpi"], extras)


def test_readme_python_names_exist():
    import clrf
    used = set()
    for lang, lines in fenced_blocks(README.read_text()):
        if lang == "python":
            used |= set(re.findall(r"\bclrf\.([A-Za-z_]\w*)", "\n".join(lines)))
    assert used, "no clrf.NAME in the README's Python block"
    missing = sorted(n for n in used if not hasattr(clrf, n))
    assert not missing, f"README's Python block uses clrf.{missing}, which do not exist"


def _strip_code(text):
    text = re.sub(r"^\s*```.*?^\s*```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _anchors(path):
    """GitHub-style heading anchors of a Markdown file."""
    out = set()
    for line in _strip_code(path.read_text()).splitlines():
        m = re.match(r"^#+\s+(.*)", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            out.add(slug)
    return out


def broken_links(doc, text=None):
    """Relative links of a Markdown file that point at no file (or at no heading)."""
    text = _strip_code(doc.read_text() if text is None else text)
    targets = re.findall(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text)
    targets += re.findall(r"<img[^>]*\bsrc=\"([^\"]+)\"", text)
    bad = []
    for t in targets:
        if re.match(r"^[a-z]+:", t):
            continue
        path, _, anchor = t.partition("#")
        dest = (doc.parent / path).resolve() if path else doc
        if not dest.exists():
            bad.append(f"{t}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{t}: no heading with anchor #{anchor}")
    return bad


@pytest.mark.parametrize("doc", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(doc):
    bad = broken_links(doc)
    assert not bad, f"{doc.relative_to(ROOT)}: " + "; ".join(bad)


def test_link_checker_finds_broken_links():
    text = ("[ok](docs/guide.md#installing) [gone](docs/no_such_page.md) "
            "[anchor](docs/guide.md#no-such-heading) <img src=\"tools/no.png\"> "
            "[web](https://example.org/x) `[code](not/checked.md)`")
    bad = broken_links(README, text)
    assert len(bad) == 3, bad
    assert any("no_such_page" in b for b in bad) and any("no-such-heading" in b for b in bad)


def test_readme_length():
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines; keep it at most " \
                                  f"{MAX_README_LINES} and move detail to docs/"
