"""Energy terms of the incremental potential: one folder per energy, its NumPy reference and its
Taichi kernels side by side.

Every folder ``sim_core/energies/<energy>/`` holds

- ``reference.py``: the potential class in NumPy (value, gradient, projected Hessian; the reference
  and the test oracle of the kernels), following the contract of :mod:`sim_core.energies.base`;
- ``kernel.py`` / ``fused_*kernel.py`` where the energy has them: its Taichi twin (same arrays on
  Taichi kernels) and its fused Newton part (energy, gradient and exact Hessian into CSR slots);
- ``__init__.py``: the public classes and the energy's registration (``ELASTIC_KINDS``, read by
  :mod:`sim_core.energies.registry`; ``FUSED_KERNELS``, read by :mod:`sim_core.fused_elastic`).

The energies: ``neohookean`` (the gel), ``membrane`` (StVK and spring), ``hinge_bending``,
``kirchhoff_bending``, ``contact`` (vertex-triangle, edge-edge, plane), ``friction``, ``damping``,
``inertia``, ``gravity``, ``sphere_contact``. Taichi infrastructure shared by all kernels (device
buffers, cached launches, small linear algebra, block projection, broad phase) is
:mod:`sim_core.ti_kernels`. Importing a package here does not import Taichi; only its kernel modules do.
"""
