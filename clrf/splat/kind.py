"""Gaussian splatting as the registry lists it (clrf/registry.py): its configuration section,
presets and settings per scene preset, factories, memory estimate and its own export (the
Gaussians as a 3DGS PLY, an SPZ or a .splat file). It trains on whole views (Kind.batches
"views"), needs world-space cameras (Kind.world_cameras: a forward-facing capture comes without
NDC) and starts from the scene's sparse points (Kind.wants_points) unless splat.init says
otherwise."""
from __future__ import annotations

from ..interface import Export, Kind
from . import budget
from .config import SPLAT_PRESETS, SplatConfig

SCENE_PRESETS = {
    "procedural": {"preset": "tiny"},
    "tiny": {"preset": "tiny"},
    # forward-facing captures (fern: 17 views of 504x378; 60 s runs on 2 vCPUs of a Xeon,
    # docs/splat.md): triangulated points sized by their 3 nearest neighbours cover up to
    # ~70 px each, so a step took 0.42 s (103 steps, 19.04 dB); at most 4 px, 0.2 s (313
    # steps, 20.94 dB). Random first Gaussians fill the frusta: 100k made 65 steps (13.8 dB),
    # 20k 239 (18.7 dB)
    "forward_facing": {"init_points": 20000, "init_max_pixels": 4.0},
}


def wants_points(cfg) -> bool:
    """A run starts from the scene's sparse points unless splat.init is "random" or a splat
    file (splat.init_ply)."""
    return cfg.splat.init != "random" and not cfg.splat.init_ply


def create(device, cfg, ds, background):
    from .model import create_model
    return create_model(device, cfg, ds, background)


def check(cfg, ds, caps):
    from .model import check_inputs
    check_inputs(cfg, ds, caps)


def from_state(device, state, cfg):
    from .model import model_from_state
    return model_from_state(device, state, cfg)


def write_splats(model, path, state=None, views=None):
    from .model import write_splats as write
    return write(model, path)


def write_web(model, path, state=None, views=None):
    from .web import write_web as write
    return write(model, state, path, views)


def check_web(path):
    from .web import check_web_dir, need_viser
    need_viser()
    check_web_dir(path)


def programs(device, cfg):
    """Every program a splat run of ``cfg`` asks ``device`` for (Kind.programs): projection and
    rasteriser at the device's default tile, the loss, the densification statistics, the
    rows shape's depth sort and Adam, the colour transform per image (splat.exposure), the
    bilateral grids per image at the section's luminance bins (splat.bilateral_grid), the
    projection with the camera's gradient (splat.pose_opt), the anti-aliased projection
    (splat.antialiased), the rasteriser with depth (renders that ask for it) and with absolute
    screen gradients (splat.absgrad); the options' programs listed whatever cfg says: the
    offline builds cover every program a run may build)."""
    from ..corrections import bilateral, exposure
    from ..runtime import optim, sort
    from . import loss, raster
    degree, tile = cfg.splat.sh_degree, raster.default_tile(device)
    for aa in (False, True):    # splat.antialiased
        raster.programs(device, degree, tile, aa, cfg.splat.aa_filter2d)
        raster.pose_program(device, degree, tile, aa, cfg.splat.aa_filter2d)
    raster.raster_program(device, degree, tile, depth=True)
    raster.raster_program(device, degree, tile, absgrad=True)
    loss.program(device)
    device.program("splat_train.cl")                       # model.py
    sort.program(device)
    optim.program(device, "adam")
    exposure.program(device)                               # clrf/corrections/exposure.py
    bilateral.program(device, cfg.splat.bilateral_grid_shape[2])   # corrections/bilateral.py


def scene_file(path):
    """The checkpoint state of a splat file (scenefile.py), or None where ``path`` is not one."""
    from .scenefile import is_scene_file, state_from_file
    return state_from_file(path) if is_scene_file(path) else None


class Distributed:
    """Splats over MPI ranks (clrf/splat/distributed.py): the Gaussians split into a shard per
    rank, a batch of one view per rank; the checks of a run's settings and the factories."""

    def __init__(self, comm):
        self.comm = comm
        self.brick = (comm.Get_rank(), comm.Get_size())   # checkpoint.load(brick=...)

    def check(self, cfg):
        """ValueError naming the setting when ``cfg`` cannot run on these ranks."""
        from .distributed import check_settings
        check_settings(cfg, self.comm.Get_size())

    def rank_config(self, cfg):
        """The configuration the memory guard checks against each rank: the whole run's (a
        rank holds its shard, and the whole table once while the first Gaussians are cut)."""
        return cfg

    def create(self, device, cfg, ds, background):
        from .distributed import DistSplatModel
        from .model import create_model
        m = create_model(device, cfg, ds, background, cls=DistSplatModel)
        return m._join_ranks(self.comm, m.max_count).take_shard()

    def from_state(self, device, state, cfg):
        from .distributed import DistSplatModel
        m = DistSplatModel.from_state_dict(device, state)
        own = state.get("shard") or {}
        m._join_ranks(self.comm, int(state["max_count"]))
        if int(own.get("ranks", 0)) != self.comm.Get_size():   # a joined checkpoint: cut it
            m.take_shard()
        return m


SPLATS = Export(help="3D Gaussian splats, the format by the ending: .ply (the standard 3DGS "
                     "PLY layout, x, y, z, nx, ny, nz, f_dc_0..2, f_rest_*, opacity, "
                     "scale_0..2, rot_0..3), .spz (Niantic's compressed SPZ), .glb / .gltf (glTF "
                     "2.0, KHR_gaussian_splatting), .compressed.ply (SuperSplat's) or .splat "
                     "(antimatter15's, SH degree 0)",
                suffix=(".ply", ".spz", ".glb", ".gltf", ".compressed.ply", ".splat"),
                write=write_splats)

WEB = Export(help="a new folder whose index.html shows the splat scene in a browser from any "
                  "static file server, drawn by viser's web client (needs clrf[web]; cameras "
                  "from --data or the run's)", suffix="/", write=write_web, check=check_web,
             wants_views=True)

KIND = Kind(name="splat", title="3D Gaussian splatting (tile rasteriser, whole views)",
            config=SplatConfig, presets=SPLAT_PRESETS, scene_presets=SCENE_PRESETS,
            create=create, from_state=from_state, memory=budget.memory,
            exports={"splats": SPLATS, "web": WEB}, batches="views", check=check, world_cameras=True,
            wants_points=wants_points, programs=programs, distributed=Distributed,
            scene_file=scene_file)
