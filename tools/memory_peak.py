"""Measure the peak resident memory of a `clrf train` run against the memory guard's prediction.

Runs ``python -m clrf.cli train ARGS`` as a child, samples its resident set (/proc/PID/status
VmRSS) every 0.2 s, and on exit takes the kernel's own peak (the child's ru_maxrss from
wait4). The child's stderr holds the guard's line ``clrf: memory: predicted peak ...``; the
record keeps that prediction, the measured peak and their ratio, and the RSS samples with the
training log lines (to see which phase the peak falls in), and the run's own count of its
device buffers and memory pool at their peak (its ``device memory:`` line: on a GPU the card's
memory it needed; on a CPU the part of the resident set that grows with the model). A child
that grows past ``--cap`` GiB is killed (the machine is shared), and the record says so.

    python tools/memory_peak.py --name tiny_lego --cap 8 -- \\
        --data $CLRF_DATA/tiny_lego --max-seconds 30 --out /tmp/m/tiny
    -> tools/results/memory/tiny_lego.json

``--set`` and every other `clrf train` option go after ``--``. ``--table [FOLDER]`` prints the
records as a markdown table (docs/memory.md).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRED = re.compile(r"memory: predicted peak ([0-9.]+) GiB")
# the run's own count of its device buffers and pool (clrf/runtime/devmem.py), at training's end
DEVICE = re.compile(r"device memory: peak ([0-9.]+) GiB held .*\(([0-9.]+) GiB in use\)")


def rss_kib(pid: int) -> int:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def measure(train_args, cap_gib: float, period: float = 0.2) -> dict:
    """Run `clrf train train_args`; returns the record (see the module docstring)."""
    cmd = [sys.executable, "-m", "clrf.cli", "train"] + list(train_args)
    t0 = time.time()
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, bufsize=1)
    lines, samples, killed = [], [], [False]

    def read():
        for line in p.stdout:
            lines.append((round(time.time() - t0, 2), line.rstrip()))
            sys.stderr.write(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    while True:
        try:
            pid, status, ru = os.wait4(p.pid, os.WNOHANG)
        except ChildProcessError:
            break
        if pid:
            break
        r = rss_kib(p.pid)
        samples.append((round(time.time() - t0, 2), r))
        if r > cap_gib * (1 << 20) and not killed[0]:
            killed[0] = True
            p.kill()
        time.sleep(period)
    reader.join(timeout=5)
    p.returncode = os.waitstatus_to_exitcode(status)
    text = "\n".join(x for _, x in lines)
    m = PRED.findall(text)
    measured = ru.ru_maxrss * 1024
    rec = {"command": "clrf train " + " ".join(train_args), "rc": p.returncode,
           "killed_at_cap_gib": cap_gib if killed[0] else None,
           "measured_peak_bytes": measured,
           "predicted_peak_bytes": int(float(m[-1]) * (1 << 30)) if m else None,
           "wall_s": round(time.time() - t0, 1),
           "rss_samples_kib": samples[::max(1, len(samples) // 400)], "log": lines}
    dm = DEVICE.findall(text)
    if dm:
        rec["device_peak_held_bytes"] = int(float(dm[-1][0]) * (1 << 30))
        rec["device_peak_in_use_bytes"] = int(float(dm[-1][1]) * (1 << 30))
    if rec["predicted_peak_bytes"]:
        rec["ratio_predicted_over_measured"] = round(rec["predicted_peak_bytes"] / measured, 3)
    return rec


def table(folder) -> str:
    """Markdown table (config, predicted, measured, ratio) of the records in ``folder``."""
    g = float(1 << 30)
    rows = ["| config | predicted peak | measured peak (ru_maxrss) | predicted / measured |",
            "| --- | --- | --- | --- |"]
    for f in sorted(Path(folder).glob("*.json")):
        r = json.loads(f.read_text())
        pred = r.get("predicted_peak_bytes")
        rows.append(f"| {f.stem} | {pred / g:.3f} GiB | {r['measured_peak_bytes'] / g:.3f} GiB "
                    f"| {r.get('ratio_predicted_over_measured')} |" if pred else
                    f"| {f.stem} | - | {r['measured_peak_bytes'] / g:.3f} GiB | - |")
    return "\n".join(rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--table"]:
        print(table(argv[1] if len(argv) > 1 else ROOT / "tools" / "results" / "memory"))
        return 0
    ap.add_argument("--name", required=True, help="record name: tools/results/memory/NAME.json")
    ap.add_argument("--cap", type=float, default=8.0, help="kill the run above this many GiB")
    ap.add_argument("--results", default=str(ROOT / "tools" / "results" / "memory"))
    ap.add_argument("train_args", nargs=argparse.REMAINDER, help="-- then clrf train options")
    a = ap.parse_args(argv)
    args = a.train_args[1:] if a.train_args[:1] == ["--"] else a.train_args
    rec = measure(args, a.cap)
    out = Path(a.results)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.json").write_text(json.dumps(rec, indent=1))
    g = 1 << 30
    pred = rec["predicted_peak_bytes"]
    print(f"{a.name}: measured peak {rec['measured_peak_bytes'] / g:.3f} GiB, predicted "
          f"{pred / g if pred else float('nan'):.3f} GiB, ratio "
          f"{rec.get('ratio_predicted_over_measured')}, rc {rec['rc']}"
          f"{', killed at the cap' if rec['killed_at_cap_gib'] else ''}"
          + (f"; device memory peak {rec['device_peak_held_bytes'] / g:.3f} GiB held "
             f"({rec['device_peak_in_use_bytes'] / g:.3f} GiB in use)"
             if "device_peak_held_bytes" in rec else ""))
    return 0 if rec["rc"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
