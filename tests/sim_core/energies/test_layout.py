"""One folder per energy (sim_core/energies/<energy>/): its NumPy reference, its Taichi kernels and
its registration side by side; the registries read the folders' registrations; nothing of an
energy is left in the shared Taichi infrastructure (sim_core/ti_kernels)."""

from __future__ import annotations

import importlib
import importlib.util
import re
from pathlib import Path

import pytest

import sim_core.energies
from sim_core import fused_elastic
from sim_core.energies import registry

ENERGIES = ("neohookean", "nodal_pressure", "green_strain", "modified_stvk", "membrane", "hinge_bending",
            "kirchhoff_bending", "contact", "friction", "damping", "inertia", "gravity", "sphere_contact")
ROOT = Path(sim_core.energies.__file__).parent
SHARED_TAICHI = {"__init__", "buffers", "launch", "linalg", "block_projection", "broad_phase", "hash_grid",
                 "hash_candidates", "sweep_candidates", "pair_filters", "pcg", "band_cholesky", "envelope_cholesky",
                 "envelope_blocks", "envelope_funcs", "transfer", "copy_vectors", "device_copy", "displacement_bounds", "compaction",
                 "scan", "precision", "backtrack", "householder_projection"}


def test_every_energy_has_its_folder_and_nothing_else_is_one():
    folders = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert folders == set(ENERGIES)


@pytest.mark.parametrize("energy", ENERGIES)
def test_a_folder_holds_its_reference_and_registers_its_own_kernels(energy):
    package = importlib.import_module(f"sim_core.energies.{energy}")
    assert (ROOT / energy / "reference.py").is_file()
    for name in package.__all__:  # the public classes come from the folder's reference
        obj = getattr(package, name)
        if isinstance(obj, type):
            assert obj.__module__ == f"sim_core.energies.{energy}.reference"
    entries = [*package.FUSED_KERNELS.items(), *((k, v) for pair in package.ELASTIC_KINDS.values() for k, v in [pair])]
    for (ref_module, ref_name), (kernel_module, kernel_name) in entries:
        assert ref_module == f"sim_core.energies.{energy}.reference"
        assert hasattr(importlib.import_module(ref_module), ref_name)
        assert kernel_module.startswith(f"sim_core.energies.{energy}.")
        assert importlib.util.find_spec(kernel_module) is not None  # located without importing Taichi
        source = (ROOT / energy / (kernel_module.rsplit(".", 1)[1] + ".py")).read_text()
        assert re.search(rf"^class {kernel_name}\b", source, re.M), kernel_name


def test_the_registries_are_made_of_the_folders_registrations():
    for energy in ENERGIES:
        package = importlib.import_module(f"sim_core.energies.{energy}")
        assert package.FUSED_KERNELS.items() <= fused_elastic.FUSED_KERNELS.items()
        assert package.ELASTIC_KINDS.items() <= registry.ELASTIC_KINDS.items()
    assert set(registry.ELASTIC_KINDS) == {"stvk_membrane", "discrete_shell_bending", "stable_neohookean",
                                           "nodal_pressure_neohookean", "green_strain", "modified_stvk"}


def test_the_shared_taichi_package_holds_infrastructure_only():
    shared = Path(sim_core.energies.__file__).parents[1] / "ti_kernels"
    assert {p.stem for p in shared.glob("*.py")} == SHARED_TAICHI
