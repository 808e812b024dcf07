"""The OpenCL runtime, the bottom layer: device choice and probing (device.py,
device_probe.py), per-device tuning (tuning.py), building programs and their logs
(programs.py, buildlog.py), host memory and memory planning (hostmem.py, memory.py), ICD
registration (icd.py), argument checks (validate.py), the parameter-update kernels every model
uses (optim.py), measuring and result caches (measure.py, workload.py, selfcheck.py),
progress output (progress.py) and the one way to replace a file safely (atomicfile.py).

It imports no representation, configuration, dataset or output module: what depends on a
model kind (a workload to time, a gradient check) is passed in or registered by the layer
that owns it (docs/architecture.md)."""
