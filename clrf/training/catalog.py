"""The programs clrf builds, listed without building them: every (kernel file, defines) pair a
device with given capabilities and tuning is asked for, for offline builds with other vendors'
compilers (tools/gpu_builds.py).

Each model kind's ``Kind.programs(device, cfg)`` asks its device for the programs a run of
``cfg`` builds, through the same functions the model calls (``grid_program``,
``clrf.mlp.mlp.program``, ``clrf.hash.encoding.program``, the corrections'
``clrf.corrections.exposure.program`` ...), so the defines are the host's own. ``library_programs`` hands them a ``Recorder`` in place of a Device, runs them over every
scene preset and every preset of the kind's own section (clrf/training/config.py
``build_config``), and adds the programs outside the kinds (the trainer's batch gather, the
device probes, the benchmark kernel of tools/nerf_bench.py).

>>> entries = library_programs(caps, Tuning.for_device(caps))
>>> entries[0].source, entries[0].defines_dict(), entries[0].uses[:2]
('grid_render.cl', {'BETA_EPS': ..., ...}, ('grid synthetic', 'grid procedural'))

The capability defines (programs.build_options) are not in the entries: the builder adds them
for its target (programs.capability_defines, programs.caps_build_flags).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Entry:
    """One program: ``cl/<source>`` with ``defines`` (sorted (name, value) pairs); ``uses``
    names who asks for it. ``raw``: built as the device probes build it, with only these
    defines (no capability defines, no -I); ``only``: the implementations it is built for
    (clrf/runtime/tuning.py ``implementation`` names; empty: every one)."""
    source: str
    defines: tuple
    uses: tuple
    raw: bool = False
    only: tuple = ()

    def defines_dict(self) -> dict:
        return dict(self.defines)


class _Unbuilt:
    """What a Recorder hands back for a program: kernels are looked up, never run."""

    def __init__(self, source):
        self.source = source

    def kernel(self, name):
        return None


class Recorder:
    """A stand-in for a clrf Device (``caps``, ``tuning``, ``is_cpu``, ``program``) that
    records the programs asked of it, with ``use`` as who asked."""

    def __init__(self, caps, tuning):
        self.caps = caps
        self.tuning = tuning
        self.use = ""
        self.asked: dict = {}

    @property
    def is_cpu(self) -> bool:
        return self.caps.type == "cpu"

    def program(self, source: str, defines: dict | None = None):
        key = (source, tuple(sorted((defines or {}).items())))
        uses = self.asked.setdefault(key, [])
        if self.use not in uses:
            uses.append(self.use)
        return _Unbuilt(source)

    def entries(self) -> list:
        return [Entry(s, d, tuple(u)) for (s, d), u in self.asked.items()]


def kind_configs(kind):
    """(label, Config) for every scene preset and every preset of ``kind``'s section (its
    default first): the runs ``clrf train --preset P [--set KIND.preset=Q]`` configures."""
    from .config import PRESETS, build_config
    for scene in PRESETS:
        for own in ("", *sorted(kind.presets)):
            over = {kind.name: {"preset": own}} if own else None
            label = f"{kind.name} {scene}" + (f" {kind.name}.preset={own}" if own else "")
            yield label, build_config(scene, overrides=over)


def library_programs(caps, tuning) -> list:
    """Every program clrf builds on a device with ``caps`` (clrf.runtime.device.Capabilities)
    and ``tuning`` (clrf.runtime.tuning.Tuning), as Entry objects in the order first asked."""
    from .. import registry
    from ..runtime.device_probe import PROBE_CHAINS, PROBE_WIDTH
    rec = Recorder(caps, tuning)
    for kind in registry.kinds():
        if kind.programs is None:
            continue
        for label, cfg in kind_configs(kind):
            rec.use = label
            kind.programs(rec, cfg)
    rec.use = "trainer"
    rec.program("batch.cl")                                 # clrf/training/trainer.py
    rec.use = "tools/nerf_bench.py"                         # the FMA peak beside the MLP
    rec.program("bench.cl", {"FMA_CHAINS": 8, "FMA_VEC": caps.vector_width,
                             "FMA_ITERS": 20000 if caps.type == "cpu" else 2048})
    out = rec.entries()
    # the device probes build with their own options only (device_probe.py, programs.py)
    probe = {"PROBE_CHAINS": PROBE_CHAINS, "PROBE_WIDTH": PROBE_WIDTH}
    out.append(Entry("probe.cl", tuple(sorted(probe.items())), ("device probe",), raw=True))
    out.append(Entry("ptx_probe.cl", (), ("PTX float atomics probe",), raw=True,
                     only=("nvidia",)))
    return out


__all__ = ["Entry", "Recorder", "kind_configs", "library_programs"]
