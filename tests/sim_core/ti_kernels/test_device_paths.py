"""The CUDA launch paths of the contact, friction and broad-phase kernels' callers (device arrays kept by
``buffers.on_device``, outputs copied back; the positions read where the fused elastic terms copied them, or
copied by each) give the host path's Forming steps; run here on the CPU arch with the arch query answering "cuda"
(the loops stay serial, so the sums are the same: bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.sim_core.ti_kernels.conftest import TEST_ARCH
from tests.sim_core.ti_kernels.test_fused_elastic import _forming_steps

_CALLERS = ("sim_core.ti_backend", "sim_core.energies.friction.kernel", "sim_core.energies.contact.batch_kernel",
            "sim_core.energies.contact.setup_kernel", "sim_core.energies.contact.sides_kernel",
            "sim_core.ti_kernels.hash_grid")


@pytest.mark.skipif(TEST_ARCH != "cpu", reason=(
    "emulates the CUDA launch paths on the CPU arch and compares them with the host path, which only the CPU "
    "arch runs; under THINSHELL_TEST_ARCH=cuda the real CUDA paths run in test_fused_elastic, test_launch and "
    "test_device_copy instead"))
def test_device_launch_paths_equal_the_host_paths(ti_cpu, monkeypatch):
    import importlib

    from sim_core.energies.contact import batch_kernel, setup_kernel, sides_kernel  # noqa: F401 (imported before
    # the arch queries are changed: a module first imported after would keep the changed query as its own)
    from sim_core.energies.friction import rows_kernel
    from sim_core.energies.friction import kernel as friction_kernel
    from sim_core.ti_backend import ti

    from sim_core.fused_elastic import FusedElastic

    runs = []
    for device, offered in ((False, False), (True, True), (True, False)):
        if device:
            for name in _CALLERS:
                monkeypatch.setattr(importlib.import_module(name), "current_arch", lambda: "cuda")
            # the fused elastic terms' projected Hessian as on the host (its kernel path, the Jacobi projection, is
            # equal to round-off only: test_fused_elastic, test_block_projection)
            monkeypatch.setattr(FusedElastic, "projected_hessian_values_device", lambda self, *args: None)
        if device and not offered:  # the friction's and pair batch's own copies of the positions, not the fused terms'
            monkeypatch.setattr(friction_kernel, "positions_on_device", lambda workspace, x: None)
            monkeypatch.setattr(batch_kernel, "positions_on_device", lambda workspace, x: None)
        sim, iterations = _forming_steps("taichi-cpu", 5)
        runs.append((sim.state.x.copy(), iterations))
        if device:
            # the device paths ran: their per-thread caches hold Taichi ndarrays of the launches' arrays
            own = {"x", "rows_vertices"} if not offered else {"x_prev_every", "rows_vertices_every"}
            own |= {"coefficient", "packed", "rows_weights", "rows_tangent"}
            pairs = {"packed_sides", "packed_rows"} | ({"packed_vertices_every"} if offered else set())
            for module, names in ((friction_kernel, own),
                                  (batch_kernel, pairs | {"packed", "d", "region", "gradients", "slots"}),
                                  (setup_kernel, {"2:_place_kernel"}),
                                  # the friction's rows built on the device (a single environment's Newton loop then
                                  # reads them back once and evaluates on the host arrays)
                                  (rows_kernel, {"pairs", "vertex_body", "table"})):
                kept = module._ARRAYS.device()
                assert names <= set(kept), module.__name__
                assert all(isinstance(kept[name][1], ti.lang._ndarray.ScalarNdarray) for name in names)
    (x_host, it_host), *device_runs = runs
    assert sum(it_host) > 5
    for x_device, it_device in device_runs:
        assert it_device == it_host
        np.testing.assert_array_equal(x_device, x_host)
