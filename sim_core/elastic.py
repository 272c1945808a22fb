"""Elastic terms of a model: membrane + bending per sheet, Stable Neo-Hookean per solid.

Builds the potentials from the model's current material parameters and maps global parameter
names (``sheet.bending_stiffness``) onto each potential's own parameter names (``bending_stiffness``)
for the adjoint.

Sheet bending model: ``"kirchhoff"`` (default, :class:`KirchhoffBending`: plate energy with the
sheet's Poisson ratio) or ``"hinge"`` (:class:`DiscreteShellBending`), from the constructor argument
or else ``model.meta["bending_model"]`` (one name for all sheets, or a dict sheet name -> name).

Solid element: ``model.meta["solid_element"]`` (one name for all solids, or a dict solid name -> name), one
of :data:`SOLID_ELEMENTS`; default ``"stable_neohookean"`` (linear tets, which lock at nu -> 0.5);
``"nodal_pressure_neohookean"`` is the average-nodal-pressure tet that does not
(:mod:`sim_core.energies.nodal_pressure`); ``"green_strain"`` Saint Venant-Kirchhoff and ``"modified_stvk"`` its
volumetric term in ``ln J`` (:mod:`sim_core.energies.green_strain`, :mod:`sim_core.energies.modified_stvk`).
"""

from __future__ import annotations

import copy

import numpy as np

from sim_core.energies.base import SplitPotential, declares
from sim_core.energies.hinge_bending.reference import DiscreteShellBending, plastic_update
from sim_core.energies.kirchhoff_bending.reference import KirchhoffBending
from sim_core.energies.membrane.reference import SpringMembrane, StVKMembrane
from sim_core.energies.registry import make_elastic_potential
from sim_core.errors import ConfigError
from sim_core.model import Model
from sim_core.workspace import Workspace


SOLID_ELEMENTS: tuple[str, ...] = ("stable_neohookean", "nodal_pressure_neohookean", "green_strain", "modified_stvk")
"""Elastic kinds (:data:`sim_core.energies.registry.ELASTIC_KINDS`) a solid body may take."""


class ElasticTerms:
    """The model's elastic potentials.

    Args:
        model: the scene model (rest shape ``x_rest`` and body materials are read once).
        bending_model: ``"kirchhoff"`` or ``"hinge"`` for every sheet; ``None`` reads
            ``model.meta.get("bending_model", "kirchhoff")`` (a name or a dict sheet -> name).
        workspace: where the potentials keep their evaluations (:mod:`sim_core.workspace`; the
            solver's), or None for one of these terms' own.

    Raises:
        ConfigError: unknown bending model or solid element name.
    """

    BENDING_MODELS = ("kirchhoff", "hinge")

    def __init__(self, model: Model, bending_model: str | None = None, workspace: Workspace | None = None) -> None:
        self.model = model
        self.workspace = Workspace() if workspace is None else workspace
        choice = model.meta.get("bending_model", "kirchhoff") if bending_model is None else bending_model
        self.bending_model: dict[str, str] = {}
        self.membranes: dict[str, StVKMembrane] = {}
        self.solids: dict[str, object] = {}  # StableNeoHookean or NodalPressureNeoHookean
        self.hinges: dict[str, np.ndarray] = {}
        self._bending: dict[str, KirchhoffBending | DiscreteShellBending] = {}
        for b in model.bodies.values():
            m = b.material
            if b.kind == "sheet":
                form = model.meta.get("membrane", {}).get(b.name)
                if form is not None and form.get("model") == "spring":
                    # ThinShellLab's edge/area springs (task scenes that ask for them)
                    self.membranes[b.name] = SpringMembrane(
                        b.triangles, b.edges, model.x_rest, form["k_length"], form["k_area"]
                    )
                else:
                    self.membranes[b.name] = StVKMembrane(
                        b.triangles, model.x_rest, m["youngs_modulus"], m["poisson_ratio"], m["thickness"]
                    )
                if b.hinges is not None and b.hinges.shape[0] > 0:
                    self.hinges[b.name] = b.hinges
                kind = choice.get(b.name, "kirchhoff") if isinstance(choice, dict) else choice
                if kind not in self.BENDING_MODELS:
                    raise ConfigError(f"sheet {b.name!r}: unknown bending_model {kind!r}; use one of {self.BENDING_MODELS}")
                self.bending_model[b.name] = kind
            elif b.kind == "solid":
                element = model.meta.get("solid_element", "stable_neohookean")
                element = element.get(b.name, "stable_neohookean") if isinstance(element, dict) else element
                if element not in SOLID_ELEMENTS:
                    raise ConfigError(f"solid {b.name!r}: unknown solid_element {element!r}; use one of {SOLID_ELEMENTS}")
                self.solids[b.name] = make_elastic_potential(element, b.tets, model.x_rest, m["youngs_modulus"],
                                                             m["poisson_ratio"])
        for pot in [*self.membranes.values(), *self.solids.values()]:
            pot.workspace = self.workspace

    def bending(self, name: str, theta_bar: np.ndarray | None) -> KirchhoffBending | DiscreteShellBending:
        """Bending potential of sheet ``name`` with rest angles ``theta_bar`` (rad, shape ``(h,)``).

        The potential (rest weights, hinge arrays) is built once per sheet and its rest angles are
        replaced per call, so the solver's cached sparsity pattern stays valid.
        """
        pot = self._bending.get(name)
        if pot is None:
            b = self.model.bodies[name]
            m = b.material
            if self.bending_model[name] == "kirchhoff":
                pot = KirchhoffBending(b.triangles, self.hinges[name], self.model.x_rest, m["bending_stiffness"],
                                       m["poisson_ratio"], theta_bar)
            else:
                pot = DiscreteShellBending(self.hinges[name], self.model.x_rest, m["bending_stiffness"], theta_bar)
            pot.workspace = self.workspace
            self._bending[name] = pot
            return pot
        if theta_bar is None:
            theta_bar = np.zeros(self.hinges[name].shape[0])
        theta_bar = np.asarray(theta_bar, dtype=float)
        if theta_bar.shape != pot.hinge_theta_bar.shape or not np.all(np.isfinite(theta_bar)):
            raise ValueError(f"sheet {name!r}: rest angles must be finite with shape {pot.hinge_theta_bar.shape}")
        clone = copy.copy(pot)
        clone.hinge_theta_bar = theta_bar
        return clone

    def potentials(self, hinge_theta_bar: dict[str, np.ndarray], skip: frozenset[str] = frozenset()) -> list:
        """The elastic potentials for one step, given the rest angles of the state: all of them, but
        those of the bodies named in ``skip`` (sleeping bodies, :mod:`sim_core.sleeping`)."""
        out: list = [p for name, p in self.membranes.items() if name not in skip]
        # a split solid (the nodal-pressure gel) enters as its parts, so a fused kernel takes its shear part
        out += [q for name, p in self.solids.items() if name not in skip
                for q in (p.parts() if declares(p, SplitPotential) else (p,))]
        out += [self.bending(name, hinge_theta_bar.get(name)) for name in self.hinges if name not in skip]
        return out

    def body_energy(self, name: str, x: np.ndarray, hinge_theta_bar: dict[str, np.ndarray]) -> float:
        """The elastic energy (J) of body ``name`` at positions ``x`` ``(n, 3)`` m: its membrane,
        solid and bending terms (0 for a body without any)."""
        terms = [d[name] for d in (self.membranes, self.solids) if name in d]
        if name in self.hinges:
            terms.append(self.bending(name, hinge_theta_bar.get(name)))
        return float(sum(p.energy(x) for p in terms))

    def parameter_terms(self, name: str, hinge_theta_bar: dict[str, np.ndarray]) -> list[tuple[object, str]]:
        """Potentials that depend on global parameter ``name`` and their local parameter names."""
        body, _, key = name.partition(".")
        out: list[tuple[object, str]] = []
        if body in self.membranes and key in self.membranes[body].parameter_names:
            out.append((self.membranes[body], key))
        if body in self.hinges and key in self.bending(body, hinge_theta_bar.get(body)).parameter_names:
            out.append((self.bending(body, hinge_theta_bar.get(body)), key))
        if body in self.solids and key in ("youngs_modulus", "poisson_ratio"):
            out.append((self.solids[body], key))
        return out

    def plastic_update(self, x: np.ndarray, hinge_theta_bar: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Bending plasticity after a step (DESIGN.md): returns the new rest angles per sheet."""
        out = {}
        for name in self.hinges:
            yield_angle = self.model.bodies[name].material.get("yield_angle", np.inf)
            tb = hinge_theta_bar.get(name)
            if tb is None:
                tb = np.zeros(self.hinges[name].shape[0])
            if np.isfinite(yield_angle):
                theta = self.bending(name, tb).theta(x)
                out[name] = plastic_update(theta, tb, yield_angle)
            else:
                out[name] = np.array(tb)
        return out
