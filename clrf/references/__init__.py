"""Float64 numpy references of clrf's kernels, written independently of the OpenCL C sources:
the oracle the tests compare every kernel with, and what the grid's gradient self-check
(clrf/grid/selfcheck.py) compares the device with at run time. numpy only; nothing here runs
on a device."""
