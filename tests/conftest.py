"""Shared fixtures: the session's device, chosen by CLRF_DEVICE (default: the device ``clrf
train`` picks for the grid: the fastest working device by its probe figure and, among equals,
by the grid workload), and the same kernel tests on every OpenCL implementation.

The kernel-vs-reference modules (EVERY_IMPL_MODULES) run once per OpenCL implementation
present: the session device, then one device of each other implementation (PoCL, Intel's CPU
runtime, Mesa's rusticl, ...; clrf/testing/impls.py), as the ``device`` fixture's parameter.
A slow software implementation runs only the small tests in SLOW_IMPL_TESTS. CLRF_TEST_IMPLS
narrows it: ``default`` (the session device only) or a comma list of
implementation names (``pocl,intel``). Oclgrind is not among them: the simulator runs every
kernel once, small, under its race and API checks (tests/test_oclgrind.py).
"""
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# The tests test the installed clrf, never this checkout: child processes started with
# `python -m ...` from the checkout must not import it either (Python 3.11+; older ones put
# the working folder first, which the tests avoid by not starting children there)
os.environ["PYTHONSAFEPATH"] = "1"
SOURCE_TREE_VAR = "CLRF_TEST_SOURCE_TREE"   # =1: a developer's explicit run on the checkout
RUN_CACHE_VAR = "CLRF_TEST_RUN_CACHE"       # the run's cache folder, made by the controller

import clrf  # noqa: E402
from clrf.testing import impls  # noqa: E402


def installed_outside_checkout() -> str | None:
    """Why the imported clrf is not an install outside this checkout, or None when it is."""
    where = Path(clrf.__file__).resolve().parent
    if where == (ROOT / "clrf").resolve():     # (a venv inside the checkout is an install)
        return (f"the tests imported clrf from the checkout ({where}), not from an install. "
                f"Install clrf (`bash tools/setup.sh test`, a non-editable `pip install .`) and "
                f"run the tests with the installed environment's pytest (`.venv/bin/pytest -q`, "
                f"not `python -m pytest` from the checkout, which imports the folder it runs "
                f"in); {SOURCE_TREE_VAR}=1 runs them on the checkout on purpose")
    return None


def pytest_configure(config):
    why = installed_outside_checkout()
    if why and os.environ.get(SOURCE_TREE_VAR) != "1":
        pytest.exit(f"clrf: {why}", returncode=4)
    if why:   # children import the checkout too
        print(f"clrf: {SOURCE_TREE_VAR}=1: testing the checkout at {clrf.__file__}",
              file=sys.stderr)
        os.environ["PYTHONPATH"] = os.pathsep.join(
            [str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    # The run's devices are chosen once, by the controller (or the only process), and handed
    # to every pytest-xdist worker (pytest_configure_node), so that all collect the same tests.
    # Workers choosing for themselves measured the devices' workloads while the other worker
    # ran on the same cores; where two implementations are within a few per cent (PoCL and
    # Intel's CPU runtime on a Xeon) they chose differently and xdist stopped ("Different tests
    # were collected").
    worker = getattr(config, "workerinput", None)
    if worker is not None and "clrf_devices" in worker:
        impls.fix(json.loads(worker["clrf_devices"]))
        config.clrf_devices = json.loads(worker["clrf_devices"])
    else:
        config.clrf_devices = impls.choose(
            with_others=os.environ.get("CLRF_TEST_IMPLS", "all").strip().lower() != "default")
        # the run's cache folder, inherited by the workers (started after this hook); a
        # developer's CLRF_TEST_RUN_CACHE=DIR keeps one between runs (compiled kernels, probe
        # figures and verdicts then carry over: not for CI, which measures a cold run)
        if not os.environ.get(RUN_CACHE_VAR):
            config.clrf_run_cache = tempfile.mkdtemp(prefix="clrf-test-cache-")
            os.environ[RUN_CACHE_VAR] = config.clrf_run_cache


def pytest_unconfigure(config):
    folder = getattr(config, "clrf_run_cache", None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(RUN_CACHE_VAR, None)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """pytest-xdist, in the controller: the run's devices for this worker (pytest_configure)."""
    node.workerinput["clrf_devices"] = json.dumps(node.config.clrf_devices)

# `pytest -n auto` (pytest-xdist, in the test extra): a worker per core, at most 4 (each worker's
# OpenCL runtime threads over every core, and the real-scene tests hold gigabytes), and a test
# file's tests on one worker (--dist loadfile) so that a module's fixtures, such as the offline
# GPU builds, are made once. The kernel builds are single-threaded: two workers keep 2 cores busy
MAX_WORKERS = 4


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    return max(1, min(os.cpu_count() or 1, MAX_WORKERS))


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    if getattr(config.option, "numprocesses", None) and getattr(config.option, "dist", None) == "no":
        config.option.dist = "loadfile"


# Mesa's rusticl shows its software device only when asked; set before any platform listing
os.environ.setdefault("RUSTICL_ENABLE", "llvmpipe")

EVERY_IMPL_MODULES = {
    "test_render", "test_grid_ops", "test_grid_grad_slots", "test_march_alpha", "test_background",
    "test_bricks", "test_nerf_mlp", "test_nerf_encode", "test_nerf_sample",
    "test_nerf_composite", "test_selfcheck", "test_build_log", "test_stability",
    "test_hash_encode", "test_hash_kernels",
    "test_splat_kernels", "test_splat_loss", "test_sort", "test_splat_exposure",
    "test_splat_pose", "test_splat_antialias", "test_splat_strategy", "test_hash_exposure",
    "test_mlp_gpu", "test_splat_targets", "test_bilateral", "test_hash_pose", "test_ray_pose",
    "test_nerf_corrections", "test_grid_pose", "test_grid_exposure",
}
# a slow software device (rusticl's llvmpipe measures ~1 % of PoCL's FMA figure, compiles each
# program variant for seconds and held 9 GB on the 128^3 test) runs the small kernel-vs-reference
# tests of every kernel family: both grid backward paths, NeRF's kernels, the self-check
SLOW_IMPL_TESTS = {
    "test_forward_vs_reference", "test_backward_vs_finite_differences",
    "test_homogeneous_slab_closed_form", "test_geometry_cases", "test_empty_grid",
    "test_forward_matches_reference", "test_backward_matches_reference",
    "test_encode_matches_reference", "test_encode_backward_matches_reference",
    "test_stratified_matches_reference", "test_importance_matches_reference",
    "test_mse_mode_loss_and_gradient", "test_both_gradient_paths_pass",
    "test_march_matches_reference", "test_packed_composite_matches_reference",
    "test_splat_project_matches_reference", "test_splat_binning_matches_reference",
    "test_splat_rasterize_matches_reference", "test_splat_rasterize_backward_matches_reference",
    "test_small_network_under_every_pass", "test_device_loss_matches_twin",
    "test_splat_rows_shape_with_small_tiles", "test_backward_matches_the_twin",
    "test_apply_and_backward_match_the_twin",
}

def pytest_generate_tests(metafunc):
    """The kernel modules' tests take every implementation as the ``device`` parameter."""
    module = metafunc.module.__name__.rsplit(".", 1)[-1]
    if module not in EVERY_IMPL_MODULES or "device" not in metafunc.fixturenames:
        return
    names = ["default"] + [n for n in impls.others(os.environ.get("CLRF_TEST_IMPLS", "all"))
                           if metafunc.function.__name__ in SLOW_IMPL_TESTS
                           or not impls.is_slow(n)]
    metafunc.parametrize("device", names, indirect=True, scope="session")


# ---- the quick tier: `pytest -m quick -n auto` --------------------------------------------------
# The default run keeps every test. The quick selection, for the inner loop, touches every test
# module in a few minutes: in each module, the first case of every test function (its first
# parametrisation, on the session device), leaving out tests marked slow (training runs, the
# command line end to end, subprocesses: over about 4 s each on 2 vCPUs), plus any test marked
# quick by hand (how a module whose tests are all slow is touched). tests/test_suite_tiers.py
# checks that every module is touched.


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    seen = set()
    for item in items:
        if item.get_closest_marker("quick"):
            continue
        fn = getattr(item, "originalname", item.name)
        key = (item.nodeid.split("::", 1)[0], item.cls.__name__ if item.cls else "", fn)
        callspec = getattr(item, "callspec", None)
        on_default = callspec is None or callspec.params.get("device", "default") == "default"
        if key in seen or not on_default or item.get_closest_marker("slow"):
            continue
        seen.add(key)
        item.add_marker(pytest.mark.quick)



@pytest.fixture(scope="session", autouse=True)
def _own_tuning_cache(tmp_path_factory):
    """Tests never read the user's tuned tiles (clrf/mlp/autotune.py) or cached verdicts: one
    empty cache folder for the whole run, made in the controller and shared by its workers
    (pytest_configure), so that each kernel is compiled once per run (PoCL's and pyopencl's
    binary caches are safe for concurrent use) and each device probed and checked once."""
    old = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = os.environ.get(RUN_CACHE_VAR) or str(
        tmp_path_factory.mktemp("xdg_cache"))
    yield
    if old is None:
        del os.environ["XDG_CACHE_HOME"]
    else:
        os.environ["XDG_CACHE_HOME"] = old


@pytest.fixture(scope="session")
def device(request):
    """The session device ("default": what ``clrf train`` picks for the grid) or one device of
    another implementation, by name."""
    name = getattr(request, "param", "default")
    if name == "default":
        return impls.default_device()
    return impls.device_of(name)


@pytest.fixture(scope="session")
def device_gpu_path(device):
    """The session device running the GPU code path of the grid renderer on any device: float
    atomics into the gradient buffers (grad_slots 0), no per-sample record, and the GPU shape
    (gpu_kernels: colours per corner, SH_PER_CORNER in cl/march.h)."""
    return device.with_tuning(grad_slots=0, sample_record=False, gpu_kernels=True)


@pytest.fixture(scope="session", params=["default_path", "gpu_path"])
def render_device(request, device, device_gpu_path):
    """Both code paths of the grid backward: the device's own tuning (on CPU devices private
    gradient copies + the per-sample record) and the GPU path."""
    return device if request.param == "default_path" else device_gpu_path


@pytest.fixture(scope="session")
def data_dir():
    """$CLRF_DATA (the shared real scenes); tests that need it skip with the reason if unset."""
    p = os.environ.get("CLRF_DATA")
    if not p or not Path(p).is_dir():
        pytest.skip("CLRF_DATA is not set to the shared data folder (see ../shared/data/README.md)")
    return Path(p)


@pytest.fixture(scope="session")
def scene(data_dir):
    """``scene("fern")``: that scene's folder in $CLRF_DATA; the test skips, naming the folder,
    where this copy of the data lacks it (a machine given only some scenes)."""
    def get(name: str) -> Path:
        path = data_dir / name
        if not path.exists():
            pytest.skip(f"no {name} in {data_dir} (see ../shared/data/README.md)")
        return path
    return get


# ---- the suite's cost (tools/suite_times.py) -------------------------------------------------
# `pytest --clrf-times FILE.json`: every test's setup / call / teardown wall and CPU seconds
# (this process and the children it waited for: the OpenCL runtime's threads count, and so do
# the compilers and clrf commands a test starts) and every fixture's own set-up, written by the
# controller at the end. tools/suite_times.py runs the suite with it and tabulates by file.
def pytest_addoption(parser):
    parser.addoption("--clrf-times", metavar="FILE.json", default=None,
                     help="write each test's and fixture's wall and CPU seconds there "
                          "(tools/suite_times.py makes the table)")


def _cpu_seconds() -> float:
    import resource
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


_TIMED = pytest.StashKey[dict]()


def _timing_on(config) -> bool:
    return bool(config.getoption("--clrf-times", default=None))


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef, request):
    if not _timing_on(request.config):
        yield
        return
    t0, c0 = time.perf_counter(), _cpu_seconds()
    yield
    item = getattr(request, "_pyfuncitem", None)
    if item is not None and fixturedef.argname not in ("request",):
        item.stash.setdefault(_TIMED, {}).setdefault("fixtures", []).append(
            (fixturedef.argname, fixturedef.scope, time.perf_counter() - t0,
             _cpu_seconds() - c0))


def _timed_phase(when):
    """The hook wrapper that times phase ``when`` (setup, call, teardown) of each test."""
    @pytest.hookimpl(hookwrapper=True)
    def wrapper(item):
        if not _timing_on(item.config):
            yield
            return
        t0, c0 = time.perf_counter(), _cpu_seconds()
        yield
        item.stash.setdefault(_TIMED, {})[when] = (time.perf_counter() - t0,
                                                   _cpu_seconds() - c0)
    return wrapper


pytest_runtest_setup = _timed_phase("setup")
pytest_runtest_call = _timed_phase("call")
pytest_runtest_teardown = _timed_phase("teardown")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    if not _timing_on(item.config):
        return
    timed = item.stash.get(_TIMED, {})
    report = outcome.get_result()
    if call.when in timed:
        report.user_properties.append(("clrf_cpu", timed[call.when][1]))
    if call.when == "setup" and timed.get("fixtures"):
        report.user_properties.append(("clrf_fixtures", [list(f) for f in timed["fixtures"]]))
        timed["fixtures"] = []


class _SuiteTimes:
    """The controller's (or the only process's) collector for --clrf-times."""

    def __init__(self, path):
        self.path, self.rows, self.t0 = Path(path), [], time.time()

    def pytest_runtest_logreport(self, report):
        props = dict(report.user_properties)
        self.rows.append({"nodeid": report.nodeid, "when": report.when,
                          "outcome": report.outcome, "wall": report.duration,
                          "cpu": props.get("clrf_cpu"),
                          "worker": getattr(getattr(getattr(report, "node", None),
                                                    "gateway", None), "id", None),
                          "fixtures": props.get("clrf_fixtures", [])})

    def pytest_sessionfinish(self, session):
        import platform
        from clrf.runtime.jsonfile import write_dict
        write_dict(self.path, {"elapsed": time.time() - self.t0, "started": self.t0,
                               "host": platform.node(), "cpus": os.cpu_count(),
                               "workers": getattr(session.config.option, "numprocesses", None),
                               "rows": self.rows})


@pytest.hookimpl(trylast=True)
def pytest_sessionstart(session):
    path = session.config.getoption("--clrf-times", default=None)
    if path and getattr(session.config, "workerinput", None) is None:
        session.config.pluginmanager.register(_SuiteTimes(path), "clrf_suite_times")
