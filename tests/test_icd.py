"""clrf/runtime/icd.py registers a venv's OpenCL driver (Intel's CPU runtime from PyPI) for the venv's
Python only: tested on a fake prefix and a fake system vendors folder."""
import os
import subprocess
import sys

import pytest

from clrf.runtime import icd


def _layout(tmp_path):
    prefix, system, site = tmp_path / "venv", tmp_path / "etc_vendors", tmp_path / "site"
    (prefix / "lib").mkdir(parents=True)
    (prefix / "lib" / "libintelocl.so").write_text("")
    vd = icd.vendors_dir(prefix)
    vd.mkdir(parents=True)
    (vd / "intel-cpu.icd").write_text("/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so\n")
    (vd / "intel-fpga_emu.icd").write_text("/opt/anaconda1anaconda2anaconda3/lib/x.so\n")
    system.mkdir()
    (system / "pocl.icd").write_text("libpocl.so.2\n")
    (system / "rusticl.icd").write_text("libRusticlOpenCL.so.1\n")
    return prefix, system, site


def test_register_writes_a_complete_vendors_folder(tmp_path):
    prefix, system, site = _layout(tmp_path)
    said = icd.register(prefix, system, site)
    vd = icd.vendors_dir(prefix)
    assert (vd / "intel-cpu.icd").read_text().strip() == str((prefix / "lib" / "libintelocl.so").resolve())
    assert not (vd / "intel-fpga_emu.icd").exists()
    for name in ("pocl.icd", "rusticl.icd"):             # the system's drivers stay visible
        assert (vd / name).is_symlink() and (vd / name).resolve() == (system / name).resolve()
    pth = (site / icd.PTH_NAME).read_text()
    assert "OCL_ICD_VENDORS" in pth and str(vd) in pth and "setdefault" in pth
    assert any("intel-cpu.icd" in s for s in said) and any("pocl.icd" in s for s in said)
    # idempotent: a second run gives the same folder
    icd.register(prefix, system, site)
    assert sorted(p.name for p in vd.iterdir()) == ["intel-cpu.icd", "pocl.icd", "rusticl.icd"]
    assert icd.unregister(prefix, site) and not (site / icd.PTH_NAME).exists()


def test_the_pth_line_sets_the_variable_only_when_unset(tmp_path):
    prefix, system, site = _layout(tmp_path)
    icd.register(prefix, system, site)
    line = (site / icd.PTH_NAME).read_text()
    code = f"{line.strip()}\nimport os; print(os.environ['OCL_ICD_VENDORS'])"
    env = {k: v for k, v in os.environ.items() if k != "OCL_ICD_VENDORS"}
    # -S: no site packages, so a .pth of the venv running the tests does not set it first
    out = subprocess.run([sys.executable, "-S", "-c", code], env=env, capture_output=True,
                         text=True)
    assert out.stdout.strip() == str(icd.vendors_dir(prefix))
    out = subprocess.run([sys.executable, "-S", "-c", code],
                         env={**env, "OCL_ICD_VENDORS": "/x"}, capture_output=True, text=True)
    assert out.stdout.strip() == "/x"


def test_register_without_a_driver_says_what_to_install(tmp_path):
    (tmp_path / "lib").mkdir()
    with pytest.raises(FileNotFoundError, match="intel-opencl-rt"):
        icd.register(tmp_path, tmp_path, tmp_path / "site")
