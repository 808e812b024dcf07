"""``clrf train`` flags generated from the typed configuration (clrf.training.config).

Every field of every section of :class:`clrf.training.config.Config` (``train`` and one per
model kind of the registry) becomes one flag ``--SECTION.KEY`` in an argparse group per section, with
the field's default and its source comment as the help text. The comment is the one written
beside the field in its dataclass (clrf/training/config.py, clrf/grid/config.py,
clrf/nerf/config.py, clrf/hash/config.py; plus the comment lines that continue it), so the
meaning is written once.

A flag is the same override as ``--set SECTION.KEY=VALUE``: its value goes into the same
overrides dict, parsed the same way (JSON, else the plain string; string fields take the text
as it is), and is then type-checked and range-checked by ``clrf.training.config.build_config``, so a bad
value gives the same ConfigError. Only flags the user typed appear in the overrides (argparse
``SUPPRESS`` defaults), which keeps the precedence defaults < preset < config file < command
line. Booleans use ``argparse.BooleanOptionalAction`` (``--grid.sphere_bound`` /
``--no-grid.sphere_bound``).

Why a small generator of our own rather than tyro or jsonargparse (both on PyPI, both light:
tyro brings docstring-parser and typeguard, jsonargparse PyYAML): both build the whole config
object from defaults plus flags, so a flag left at its default would override the preset and
the config file, and both report bad values in their own words rather than the ConfigError
that names the field and its range. Matching argparse to the override dict that ``--set``
already feeds is ~100 lines and adds no dependency.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import io
import json
import tokenize

from .. import registry
from ..training import config as config_mod

DEST_PREFIX = "cfg__"     # argparse dest of a generated flag: cfg__SECTION__KEY


def sections():
    """(section name, its dataclass, its one-line description) for every Config section: the
    run's, then one per registered model kind (clrf/registry.py)."""
    out = [("train", config_mod.TrainConfig,
            (inspect.getdoc(config_mod.TrainConfig) or "").split("\n")[0])]
    for k in registry.kinds():
        out.append((k.name, k.config, f"{k.title} (--model {k.name})"))
    return out


def field_comments(cls) -> dict:
    """Field name -> its comment in the class source: the ``# ...`` after the field on its line,
    plus the comment-only lines that follow it (a ``# ^ ...`` line or one indented past the
    field names), joined with spaces. Empty when the source cannot be read."""
    try:
        src = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    comments, code_lines = {}, {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = (tok.start[1], tok.string.lstrip("#").strip())
        elif tok.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
                              tokenize.ENDMARKER):
            code_lines.setdefault(tok.start[0], tok.start[1])
    names = {f.name for f in dataclasses.fields(cls)}
    out = {}
    lines = src.splitlines()
    for no, line in enumerate(lines, 1):
        name = line.strip().split(":", 1)[0].strip()
        if name not in names or no not in code_lines or ":" not in line:
            continue
        indent = code_lines[no]
        parts = [comments[no][1]] if no in comments and comments[no][0] > indent else []
        nxt = no + 1
        while nxt in comments and nxt not in code_lines:
            col, text = comments[nxt]
            if text.startswith("^"):
                parts.append(text[1:].strip())
            elif col > indent and parts:
                parts.append(text)
            else:
                break
            nxt += 1
        out.setdefault(name, " ".join(parts))
    return out


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()


def _show(v) -> str:
    return json.dumps(v)


def _json_or_text(text: str):
    """A flag value as ``--set`` reads it: JSON, else the string itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def add_config_flags(parser: argparse.ArgumentParser):
    """Add one ``--SECTION.KEY`` flag per configuration field to ``parser``, in a group per
    section, with the default and the field's comment as help. Call it after the parser's
    other arguments: the usage line lists those and then ``[--SECTION.KEY VALUE ...]``."""
    usage = parser.format_usage().split(":", 1)[1].strip()
    parser.usage = usage.replace(parser.prog, "%(prog)s", 1) + " [--SECTION.KEY VALUE ...]"
    for sect, cls, doc in sections():
        group = parser.add_argument_group(
            f"{sect} options", f"{doc}. The same as --set {sect}.KEY=VALUE; defaults shown are "
                               f"the built-in ones, which a scene preset may change.")
        comments = field_comments(cls)
        for f in dataclasses.fields(cls):
            default = _default(f)
            text = comments.get(f.name, "").replace("%", "%%")
            help_ = f"{text} (default: {_show(default)})" if text else \
                f"(default: {_show(default)})"
            kw = dict(dest=f"{DEST_PREFIX}{sect}__{f.name}", default=argparse.SUPPRESS,
                      help=help_)
            if isinstance(default, bool):
                group.add_argument(f"--{sect}.{f.name}", action=argparse.BooleanOptionalAction,
                                   **kw)
            elif isinstance(default, str):
                group.add_argument(f"--{sect}.{f.name}", metavar="TEXT", **kw)
            else:
                metavar = "JSON" if isinstance(default, (list, dict)) else "VALUE"
                group.add_argument(f"--{sect}.{f.name}", metavar=metavar, type=_json_or_text,
                                   **kw)


def config_flags(namespace) -> dict:
    """The generated flags the user gave, as ``{section: {key: value}}`` (the shape
    ``clrf.cli.parse_set`` returns)."""
    out = {}
    for dest, value in vars(namespace).items():
        if dest.startswith(DEST_PREFIX):
            sect, key = dest[len(DEST_PREFIX):].split("__", 1)
            out.setdefault(sect, {})[key] = value
    return out


def merge_overrides(*dicts) -> dict:
    """Section-wise merge of override dicts; later ones win per key."""
    out = {}
    for d in dicts:
        for sect, vals in d.items():
            out.setdefault(sect, {}).update(vals)
    return out
