"""alpha_of_tau (cl/common.h: series up to 0.7, 1 - exp(-tau) above) against float64
-expm1(-tau) from 1e-30 to 1e30: within 2 float32 ulp of the exact value everywhere."""
import numpy as np
import pyopencl.array as cla

from clrf.grid.render import grid_program
from clrf.runtime.programs import launch


class _G:   # grid_program needs only these attributes
    def __init__(self, dev):
        self.device, self.sh_degree, self.reso = dev, 0, (1, 1, 1)


def test_alpha_of_tau_accuracy(device):
    tau = np.concatenate([np.logspace(-30, 30, 4001), np.linspace(0, 2, 4001),
                          [0.5, 0.7, np.nextafter(np.float32(0.7), 1), np.log(2), np.inf]]).astype(np.float32)
    q = device.queue
    t = cla.to_device(q, tau)
    out = cla.empty(q, tau.size, np.float32)
    k = grid_program(_G(device)).kernel("march_alpha_eval")
    launch(device, k, tau.size, (np.int32(tau.size), t.data, out.data), 64)
    got = out.get().astype(np.float64)
    exact = -np.expm1(-tau.astype(np.float64))
    ulp = np.spacing(exact.astype(np.float32)).astype(np.float64)
    ulp[exact == 0] = np.finfo(np.float32).smallest_subnormal
    assert np.all(np.abs(got - exact) <= 2 * ulp), np.max(np.abs(got - exact) / ulp)
