"""`clrf train --help` lists every configuration key with its default and meaning, generated
from clrf.training.config; a generated flag is the same override as --set; bad values give ConfigError."""
import dataclasses
import json
import re

import pytest

from clrf.cli.main import build_parser, main, parse_set
from clrf.cli.config_flags import config_flags, field_comments, merge_overrides, sections
from clrf.training.config import Config, build_config


def _train_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["train", "--help"])
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())       # argparse's wrapping undone


def _all_fields():
    return [(sect, f) for sect, cls, _ in sections() for f in dataclasses.fields(cls)]


def test_every_section_of_config_is_covered():
    assert [s for s, _, _ in sections()] == Config().section_names()


def test_every_field_has_a_comment():
    # the help text comes from the comment beside each field in clrf/training/config.py: a new field
    # without one fails here
    missing = [f"{sect}.{f.name}" for sect, cls, _ in sections()
               for f in dataclasses.fields(cls) if not field_comments(cls).get(f.name)]
    assert not missing, missing


def test_help_lists_every_key_with_default_and_meaning(capsys):
    text = _train_help(capsys)
    opts = text[text.index("train options:"):]              # past the usage line
    flags = [f"--{sect}.{f.name}" for sect, f in _all_fields()]
    starts = sorted((m.start(), flag) for flag in flags
                    for m in [re.search(re.escape(flag) + r"[ ,]", opts)] if m)
    assert len(starts) == len(flags), set(flags) - {f for _, f in starts}
    defaults = Config().to_dict()
    chunks = {flag: opts[a:b] for (a, flag), (b, _) in zip(starts, starts[1:] + [(None, "")])}
    for sect, f in _all_fields():
        chunk = chunks[f"--{sect}.{f.name}"]
        assert f"(default: {json.dumps(defaults[sect][f.name])})" in chunk, chunk
        meaning = " ".join(field_comments(type(Config().section(sect)))[f.name].split())
        assert meaning.replace("%%", "%") in chunk, (meaning, chunk)


def test_booleans_are_optional_actions(capsys):
    text = _train_help(capsys)
    assert "--grid.sphere_bound, --no-grid.sphere_bound" in text
    assert "--nerf.perturb, --no-nerf.perturb" in text


def test_device_help_says_measured(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "first working GPU" not in text
    assert "fastest working device" in text and "clrf devices" in text


def test_every_command_has_working_help(capsys):
    """`clrf CMD --help` prints for every command (argparse %-formats help text: a literal %
    in it, like "i % 8 == 0" in a protocol's description, once made `clrf eval --help` crash)."""
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    assert {"train", "render", "eval", "export"} <= set(sub.choices)
    for cmd in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([cmd, "--help"])
        assert e.value.code == 0, cmd
        assert "usage: clrf " + cmd in " ".join(capsys.readouterr().out.split()), cmd


def _flags(*argv):
    return config_flags(build_parser().parse_args(["train", *argv]))


@pytest.mark.parametrize("flags,sets", [
    (["--grid.batch_size", "3000"], ["grid.batch_size=3000"]),
    (["--grid.reso", "[[32,32,32]]", "--grid.upsample_at", "[]"],
     ["grid.reso=[[32,32,32]]", "grid.upsample_at=[]"]),
    (["--grid.sphere_bound"], ["grid.sphere_bound=true"]),   # the procedural preset: false
    (["--no-train.final_eval"], ["train.final_eval=false"]),
    (["--train.max_seconds", "7.5", "--train.model", "nerf"],
     ["train.max_seconds=7.5", "train.model=nerf"]),
    (["--nerf.preset", "original", "--nerf.width", "128"],
     ["nerf.preset=original", "nerf.width=128"]),
    (["--nerf.mlp_rows", "4"], ["nerf.mlp_rows=4"]),
    (["--train.background", "[0, 0, 0]"], ["train.background=[0,0,0]"]),
])
def test_flag_equals_set(flags, sets):
    assert _flags(*flags) == parse_set(sets)
    a = build_config("procedural", None, _flags(*flags)).to_dict()
    b = build_config("procedural", None, parse_set(sets)).to_dict()
    assert a == b and a != build_config("procedural").to_dict()


def test_flag_null_and_true():
    assert _flags("--nerf.mlp_rows", "null") == parse_set(["nerf.mlp_rows=null"])
    assert _flags("--train.final_eval") == {"train": {"final_eval": True}}


def test_untyped_flags_leave_preset_and_file(tmp_path):
    # a flag the user did not type is not an override: preset < file < command line holds
    assert _flags() == {}
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"grid": {"step": 0.7}}))
    cfg = build_config("forward_facing", str(f), _flags("--grid.batch_size", "3000"))
    assert cfg.grid.lambda_tv == 5e-4 and cfg.grid.step == 0.7 and cfg.grid.batch_size == 3000
    cfg = build_config("forward_facing", str(f), _flags("--grid.lambda_tv", "0",
                                                          "--grid.step", "0.3"))
    assert cfg.grid.lambda_tv == 0.0 and cfg.grid.step == 0.3


def test_flags_after_set():
    both = merge_overrides(parse_set(["grid.step=0.2", "grid.sh_degree=1"]),
                           _flags("--grid.step", "0.4"))
    assert both == {"grid": {"step": 0.4, "sh_degree": 1}}


@pytest.mark.parametrize("flag,value,needle", [
    ("--grid.batch_size", "many", "grid.batch_size must be an integer, got 'many'"),
    ("--grid.step", "9", "grid.step = 9.0: must be in (0, 4] voxels"),
    ("--nerf.width", "100", "nerf.width = 100: must be a multiple of 16"),
    ("--train.model", "mesh", "train.model = 'mesh': must be 'grid', 'nerf', 'hash' or 'splat'"),
])
def test_bad_flag_value_is_a_config_error(tmp_path, capsys, flag, value, needle):
    rc = main(["train", "--out", str(tmp_path / "r"), "--max-seconds", "1", flag, value])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err, err
    assert not (tmp_path / "r").exists()                     # nothing written
