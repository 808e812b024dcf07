"""Register OpenCL drivers installed inside a virtual environment, without root.

Intel's oneAPI OpenCL CPU runtime comes from PyPI (``pip install intel-opencl-rt
intel-cmplr-lib-rt``, the ``intel`` extra) as ``<venv>/lib/libintelocl.so``, but its wheel's
``<venv>/etc/OpenCL/vendors/intel-cpu.icd`` names a placeholder path, and the OpenCL loader
(ocl-icd) only reads ``/etc/OpenCL/vendors`` unless ``OCL_ICD_VENDORS`` names another folder.
``register(prefix)`` makes ``<venv>/etc/OpenCL/vendors`` a complete folder: the venv's driver
with its real path, plus a link to every system ``.icd`` file (so PoCL, rusticl, ... stay
visible), and writes ``clrf-opencl-vendors.pth`` into the venv's site-packages, which points
``OCL_ICD_VENDORS`` at that folder in every Python of the venv (unless it is already set). No
system file is touched; ``unregister`` undoes it.

    python -m clrf.runtime.icd register      # what `bash tools/setup.sh intel` runs
    python -m clrf.runtime.icd unregister
"""
from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")
PTH_NAME = "clrf-opencl-vendors.pth"
# the drivers a venv can hold: (ICD file name, library under <prefix>/lib)
VENV_DRIVERS = (("intel-cpu.icd", "libintelocl.so"),)
# ICD files some wheels ship that name no usable library here (Intel's FPGA emulator)
STALE = ("intel-fpga_emu.icd",)


def vendors_dir(prefix: Path) -> Path:
    return Path(prefix) / "etc" / "OpenCL" / "vendors"


def site_packages(prefix: Path) -> Path:
    return Path(sysconfig.get_paths(vars={"base": str(prefix), "platbase": str(prefix)})["purelib"])


def register(prefix=None, system_vendors: Path = SYSTEM_VENDORS, site: Path | None = None) -> list:
    """Make the venv at ``prefix`` (default: this interpreter's) register its OpenCL drivers;
    returns what was done, one line each. Raises FileNotFoundError when it holds none."""
    prefix = Path(prefix or sys.prefix)
    vdir = vendors_dir(prefix)
    found = [(icd, prefix / "lib" / lib) for icd, lib in VENV_DRIVERS
             if (prefix / "lib" / lib).exists()]
    if not found:
        raise FileNotFoundError(
            f"no OpenCL driver in {prefix / 'lib'} (looked for "
            f"{', '.join(lib for _, lib in VENV_DRIVERS)}); install one first, e.g. "
            f"`pip install intel-opencl-rt intel-cmplr-lib-rt`")
    vdir.mkdir(parents=True, exist_ok=True)
    done = []
    for name in STALE:
        if (vdir / name).exists() or (vdir / name).is_symlink():
            (vdir / name).unlink()
            done.append(f"removed {vdir / name} (no such driver here)")
    for icd, lib in found:
        (vdir / icd).write_text(f"{lib.resolve()}\n")
        done.append(f"wrote {vdir / icd} -> {lib.resolve()}")
    own = {icd for icd, _ in found}
    for sys_icd in sorted(Path(system_vendors).glob("*.icd")):
        link = vdir / sys_icd.name
        if sys_icd.name in own:
            continue
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(sys_icd)
        done.append(f"linked {link} -> {sys_icd} (system driver kept visible)")
    site = Path(site) if site is not None else site_packages(prefix)
    site.mkdir(parents=True, exist_ok=True)
    (site / PTH_NAME).write_text(
        f"import os; os.environ.setdefault('OCL_ICD_VENDORS', {str(vdir)!r})\n")
    done.append(f"wrote {site / PTH_NAME}: OCL_ICD_VENDORS={vdir} in this venv's Python "
                f"(unless already set)")
    return done


def unregister(prefix=None, site: Path | None = None) -> list:
    """Remove the .pth file ``register`` wrote (the vendors folder stays, unused)."""
    prefix = Path(prefix or sys.prefix)
    pth = (Path(site) if site is not None else site_packages(prefix)) / PTH_NAME
    if pth.exists():
        pth.unlink()
        return [f"removed {pth}"]
    return []


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] not in (["register"], ["unregister"]):
        print(__doc__.strip().splitlines()[-2:][0].strip(), file=sys.stderr)
        print("usage: python -m clrf.runtime.icd register|unregister", file=sys.stderr)
        return 2
    try:
        lines = register() if argv[0] == "register" else unregister()
    except (FileNotFoundError, OSError) as e:
        print(f"clrf: {e}", file=sys.stderr)
        return 1
    for line in lines:
        print(f"clrf: {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
