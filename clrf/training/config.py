"""Typed, validated configuration: defaults < scene preset < config file < command line.

One dataclass per concern: the run (TrainConfig, here) and one section per model kind, each
beside its model and listed by the registry (clrf/registry.py: a kind's ``config``);
``Config`` holds them all. Every field is commented; `validate()` rejects out-of-range values
with a message naming the field. The effective configuration is written next to the outputs
(config.json) and can be fed back with --config.

A scene preset (chosen by the dataset, or --preset) sets the run's options here and each
kind's section through that kind's ``scene_presets``; a section with presets of its own
(``SECTION.preset``) is replaced whole by the named one before its other keys apply.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from .. import registry


class ConfigError(ValueError):
    """An unknown option or an out-of-range value; the message names the field and the fix."""


@dataclass
class TrainConfig:
    """The run: data, budget, evaluation, checkpoints."""
    model: str = registry.DEFAULT  # the representation (clrf/registry.py; `clrf train --help`)
    data: str = ""                # dataset path; empty: the built-in procedural scene
    preset: str = ""              # scene preset; empty: the dataset's own
    max_seconds: float = 120.0    # wall-clock training budget (evaluation excluded)
    max_iters: int = 100000       # iteration cap
    eval_every: float = 10.0      # seconds of training between evaluations
    eval_views: int = 4           # test views per periodic evaluation (all at the end)
    eval_downscale: int = 1       # periodic evaluations render views downscaled by this factor
                                  # (the final one is full size)
    final_eval: bool = True       # evaluate every test view at the end
    checkpoint_every: float = 60.0  # seconds of training between checkpoints
    seed: int = 0                 # batch sampling and initialisation seed
    background: list = field(default_factory=list)  # override the dataset background [r,g,b]
    downscale: int = 1            # load images downscaled by this integer factor
    max_train_images: int = 0     # train on the first this-many training images; 0: all
    points: str = "auto"          # sparse points of the scene (models that start from them):
                                  # "auto" the capture's own (COLMAP's points3D) when it has
                                  # them; "triangulate" also COLMAP on the training views with
                                  # their known poses where it has none (the process extra,
                                  # cached); "none" ignore them


POINT_MODES = ("auto", "triangulate", "none")   # clrf/data/triangulate.py MODES

# The scene presets and what each sets in the run's section; each model kind's own settings for
# them are its Kind.scene_presets (e.g. clrf/grid/kind.py).
PRESETS = {
    # Blender-style synthetic 360: white/black background, no NDC, no background model
    "synthetic": {},
    # the built-in procedural scene (the first run, `clrf train`): small images, a minute
    "procedural": {"train": {"max_seconds": 60.0, "eval_every": 5.0}},
    # tiny_lego (100x100 images)
    "tiny": {},
    # forward-facing (LLFF): NDC rays; periodic evaluations on 1/4-size views
    "forward_facing": {"train": {"eval_downscale": 4}},
    # unbounded real 360: a background behind the scene's box
    "real360": {},
    # unbounded real 360 whose box is meant to hold the whole scene (instant-ngp captures: the
    # aabb_scale cube)
    "real360_box": {},
}


def scene_preset(name: str) -> dict:
    """The sections a scene preset sets: the run's, then every kind's."""
    out = {k: dict(v) for k, v in PRESETS[name].items()}
    for kind in registry.kinds():
        extra = kind.scene_presets.get(name)
        if extra:
            out[kind.name] = dict(extra)
    return out


class Config:
    """The run's configuration: ``train`` (TrainConfig) and one section per registered model
    kind, ``cfg.<kind>``, that kind's dataclass."""

    def __init__(self):
        self.train = TrainConfig()
        self.sections = {k.name: k.config() for k in registry.kinds()}

    def __getattr__(self, name):
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(f"{type(self).__name__} has no section {name!r}")

    def section_names(self) -> list:
        return ["train", *self.sections]

    def section(self, name: str):
        return self.train if name == "train" else self.sections[name]

    def set_section(self, name: str, value):
        if name == "train":
            self.train = value
        else:
            self.sections[name] = value

    def to_dict(self):
        return {n: dataclasses.asdict(self.section(n)) for n in self.section_names()}

    def validate(self):
        t = self.train
        checks = [
            (t.model in self.sections, "train.model", f"must be {_choice(self.sections)}"),
            (not t.preset or t.preset in PRESETS, "train.preset", f"must be one of {sorted(PRESETS)}"),
            (t.max_seconds > 0, "train.max_seconds", "must be > 0"),
            (t.max_iters > 0, "train.max_iters", "must be > 0"),
            (t.eval_every > 0, "train.eval_every", "must be > 0"),
            (t.eval_views >= 1, "train.eval_views", "must be >= 1"),
            (t.eval_downscale >= 1, "train.eval_downscale", "must be an integer >= 1"),
            (t.checkpoint_every > 0, "train.checkpoint_every", "must be > 0"),
            (t.downscale >= 1, "train.downscale", "must be an integer >= 1"),
            (t.points in POINT_MODES, "train.points", f"must be one of {list(POINT_MODES)}"),
            (t.max_train_images >= 0, "train.max_train_images", "must be >= 0"),
            (len(t.background) in (0, 3) and all(0 <= b <= 1 for b in t.background),
             "train.background", "must be empty or three values in [0, 1]"),
        ]
        for s in self.sections.values():
            checks += s.checks()
        for ok, name, msg in checks:
            if not ok:
                value = _get(self, name)
                raise ConfigError(f"{name} = {value!r}: {msg}")
        return self


def _choice(names) -> str:
    """"'a', 'b' or 'c'"."""
    q = [repr(n) for n in names]
    return ", ".join(q[:-1]) + (" or " if len(q) > 1 else "") + q[-1]


def _get(cfg, dotted):
    sect, _, key = dotted.partition(".")
    obj = cfg.section(sect) if sect in cfg.section_names() else None
    if key.endswith("*"):
        return "..."
    return getattr(obj, key, None) if not isinstance(obj, dict) else obj.get(key)


def _merge(cfg: Config, d: dict, source: str):
    for sect, vals in d.items():
        if sect not in cfg.section_names():
            raise ConfigError(f"{source}: unknown section '{sect}'; use "
                              f"{', '.join(cfg.section_names())}")
        if not isinstance(vals, dict):
            raise ConfigError(f"{source}: '{sect}' must be an object of options, got {vals!r}")
        presets = registry.get(sect).presets if sect != "train" else {}
        if presets and "preset" in vals:
            vals = dict(vals)
            name = vals.pop("preset")
            if name not in presets:
                raise ConfigError(f"{source}: {sect}.preset = {name!r}: use one of "
                                  f"{', '.join(sorted(presets))}")
            cfg.set_section(sect, type(cfg.section(sect)).from_preset(name))
        cur = cfg.section(sect)
        cfg.set_section(sect, dataclasses.replace(cur, **_typed(cur, sect, vals, source)))


def _typed(obj, sect: str, vals: dict, source: str) -> dict:
    """``vals`` checked against the fields of dataclass ``obj``: known names, and each value of
    its field's type (an integral float is taken as an int; ``int | None`` fields take null; a
    string field takes true and false as those words)."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    out = {}
    for k, v in vals.items():
        if k not in names:
            raise ConfigError(f"{source}: unknown option '{sect}.{k}'; use one of "
                              f"{', '.join(sorted(names))}")
        cur = getattr(obj, k)
        optional = "None" in str(names[k].type)
        if v is None and optional:
            pass
        elif isinstance(cur, bool):
            if not isinstance(v, bool):
                raise ConfigError(f"{source}: {sect}.{k} must be true or false, got {v!r}")
        elif isinstance(cur, int) or (cur is None and "int" in str(names[k].type)):
            if isinstance(v, bool) or not isinstance(v, int):
                if isinstance(v, float) and v.is_integer():
                    v = int(v)
                else:
                    raise ConfigError(f"{source}: {sect}.{k} must be an integer"
                                      f"{' or null' if optional else ''}, got {v!r}")
        elif isinstance(cur, float):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"{source}: {sect}.{k} must be a number, got {v!r}")
            v = float(v)
        elif isinstance(cur, list):
            if not isinstance(v, list):
                raise ConfigError(f"{source}: {sect}.{k} must be a list, got {v!r}")
        elif isinstance(cur, str) and isinstance(v, bool):
            v = "true" if v else "false"   # JSON's true / false (--set, a config file)
        elif isinstance(cur, str) and not isinstance(v, str):
            raise ConfigError(f"{source}: {sect}.{k} must be a string, got {v!r}")
        out[k] = v
    return out


def load_config_file(path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} not found: pass an existing JSON file to --config")
    try:
        d = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(f"config file {p}: invalid JSON at line {e.lineno} column {e.colno}: "
                          f"{e.msg}; fix the file (check it with python -m json.tool)") from None
    if not isinstance(d, dict):
        raise ConfigError(f"config file {p}: expected a JSON object with sections "
                          f"{'/'.join(Config().section_names())}")
    return d


def build_config(preset: str = "", file: str | None = None, overrides: dict | None = None,
                 dataset_preset: str = "synthetic") -> Config:
    """Defaults < preset (explicit, else the dataset's) < config file < overrides."""
    cfg = Config()
    file_d = load_config_file(file) if file else {}
    name = preset or file_d.get("train", {}).get("preset", "") or dataset_preset
    if name not in PRESETS:
        raise ConfigError(f"train.preset = {name!r}: must be one of {sorted(PRESETS)}")
    _merge(cfg, scene_preset(name), f"preset '{name}'")
    if file_d:
        _merge(cfg, file_d, f"config file {file}")
    if overrides:
        _merge(cfg, overrides, "command line")
    cfg.train.preset = name
    return cfg.validate()
