"""Self-check verdicts come from the device, never from clrf (clrf/runtime/selfcheck.py):

- a check runs in a child process: its verdict comes back and is cached; a check that crashes
  the child (as a driver that segfaults would) is a failing verdict that says so, and this
  process goes on; such a device is never the default;
- an exception of clrf's own code is no verdict: ClrfBug, or InstallError when a clrf module is
  missing, with the traceback and clrf's version, and nothing is cached;
- verdicts are keyed by clrf's version and the checking code: an entry of an older clrf (the
  key of 012b9a6, without either) is not read.
"""
import json

import pytest

from clrf.grid import selfcheck as grid_check
from clrf.runtime import device_probe, selfcheck
from clrf.runtime.device import choose_device, format_devices
from clrf.testing import faults


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(device_probe, "_memo", {})
    return tmp_path / "clrf" / "selfcheck.json"


def _atomics(device):
    return device.with_tuning(grad_slots=0, sample_record=False, grad_locks=0)


@pytest.mark.slow
def test_grid_check_in_a_child_passes_and_is_cached(device, cache, monkeypatch):
    res = selfcheck.gradient_check(device, grid_check.CHECK)
    assert res.ok, res.detail
    assert res.path == selfcheck.path_name(device.tuning)
    stored = json.loads(cache.read_text())
    (key,) = stored
    assert f"|clrf{selfcheck.clrf_version()}|" in key and stored[key]["ok"] is True
    monkeypatch.setattr(selfcheck, "run_isolated", lambda d, c: pytest.fail("not cached"))
    assert selfcheck.gradient_check(device, grid_check.CHECK) == res


def test_a_crash_in_the_check_is_a_verdict_and_this_process_goes_on(device, cache):
    dev = _atomics(device)
    res = selfcheck.gradient_check(dev, faults.CRASH)
    assert not res.ok
    assert "crashed" in res.detail and "SIGSEGV" in res.detail, res.detail
    # cached, and the device is known to crash: never the default while it does
    assert selfcheck.known_wrong(dev.cl_device, [faults.CRASH]) == res.detail
    assert selfcheck.gradient_check(dev, faults.CRASH) == res


@pytest.mark.slow
def test_a_device_that_crashes_is_not_the_default_and_says_why(device, cache, monkeypatch):
    selfcheck.gradient_check(_atomics(device), faults.CRASH)
    monkeypatch.setattr(selfcheck, "_CHECKS", [faults.CRASH])
    ours = (device.platform_index, device.device_index)
    try:
        ch = choose_device("auto")
        assert (ch.platform_index, ch.device_index) != ours
    except clrf_device_error() as e:     # the only device: refused, with the reason
        assert "crashed" in str(e) and "SIGSEGV" in str(e), str(e)
        assert ": None" not in str(e)
    listing = format_devices(checks=[faults.CRASH])
    assert "FAILED: the driver crashed" in listing


def clrf_device_error():
    from clrf.runtime.device import DeviceError
    return DeviceError


def test_wrong_numbers_are_a_cached_verdict(device, cache):
    res = selfcheck.gradient_check(_atomics(device), faults.WRONG)
    assert not res.ok and "zero" in res.detail
    assert cache.exists()


@pytest.mark.parametrize("isolate", [True, False], ids=["child", "in-process"])
def test_a_bug_in_clrf_is_no_verdict(device, cache, monkeypatch, isolate):
    monkeypatch.setattr(selfcheck, "ISOLATE", isolate)
    with pytest.raises(selfcheck.ClrfBug) as e:
        selfcheck.gradient_check(_atomics(device), faults.BUG)
    msg = str(e.value)
    assert "TypeError" in msg and "Traceback" in msg and selfcheck.clrf_version() in msg
    assert "not a verdict on the OpenCL driver" in msg
    assert not cache.exists() or json.loads(cache.read_text()) == {}


@pytest.mark.parametrize("isolate", [True, False], ids=["child", "in-process"])
def test_a_missing_clrf_module_is_an_install_error(device, cache, monkeypatch, isolate):
    monkeypatch.setattr(selfcheck, "ISOLATE", isolate)
    with pytest.raises(selfcheck.InstallError) as e:
        selfcheck.gradient_check(_atomics(device), faults.MISSING)
    msg = str(e.value)
    assert "installed incompletely" in msg and "clrf.no_such_module_on_purpose" in msg
    assert "not the OpenCL driver's fault" in msg and "Reinstall" in msg
    assert not cache.exists() or json.loads(cache.read_text()) == {}
    # and nothing makes the device look wrong afterwards
    assert selfcheck.known_wrong(device.cl_device, [faults.MISSING]) is None


@pytest.mark.slow
def test_a_verdict_of_an_older_clrf_is_not_read(device, cache, monkeypatch):
    """012b9a6 cached 'ModuleNotFoundError' as a failing verdict under a key without clrf's
    version: this clrf neither reads it nor lets it bar the device."""
    key = selfcheck.check_key(_atomics(device), grid_check.CHECK)
    old = key.rsplit("|", 2)[0]          # without clrf's version and the code hash
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps({old: {"ok": False, "path": "atomics", "detail":
                                       "ModuleNotFoundError: No module named 'clrf.references'"}}))
    assert selfcheck.known_wrong(device.cl_device) is None
    assert selfcheck.gradient_check(_atomics(device), grid_check.CHECK).ok


def test_the_probe_runs_in_a_child(device, cache):
    """The probe measures in a child process: the same kind of answer as in this one."""
    pr = device_probe.measure(device.cl_device)
    assert pr.ok, pr.error
    assert pr.gflops > 0


def test_reprobe_runs_the_checks_again_and_lists_the_verdicts(device, cache):
    """`clrf devices --reprobe` re-runs each check (in a child) with the device's own tuning
    and lists every cached verdict; without it, nothing runs and a missing verdict says so."""
    from clrf.runtime.device import selfcheck_lines
    lines = selfcheck_lines(device.cl_device, device.caps, [faults.WRONG], refresh=False)
    assert len(lines) == 1 and "not run yet" in lines[0]
    lines = selfcheck_lines(device.cl_device, device.caps, [faults.WRONG], refresh=True)
    assert any("FAILED: every gradient is zero" in x for x in lines), lines
    assert selfcheck.verdicts_for(device.cl_device, faults.WRONG)
