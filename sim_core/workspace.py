"""The solver's workspace: evaluations of positions that the energy, gradient and Hessian calls share.

A Newton iteration asks every potential for its energy (line search), then for its gradient and
Hessian at the accepted point, and several potentials need the same intermediate results for all
three (deformation gradients and invariants of the gel, hinge angles of Kirchhoff bending, contact
distances and their derivatives, friction blocks). Those results are kept here, not on the
potentials: the :class:`~sim_core.solver.NewtonSolver` creates one :class:`Workspace` and hands it to
the terms it builds (:class:`~sim_core.elastic.ElasticTerms`, :class:`~sim_core.contact_set.ContactSet`,
which give it to their potentials as their ``workspace``); a potential built on its own (a test, a
benchmark) gets a private one on first use (:func:`workspace_of`).

An entry is keyed by an owner and a name, and is only a memo: it is matched against the positions
(their bytes, :func:`sim_core.energies.base.positions_key`, or an array comparison) and the
parameters it was made for before use, so an evaluation read from the workspace is the evaluation
the potential would compute. Forgetting entries changes no result, only the time.
"""

from __future__ import annotations

import weakref


class Workspace:
    """Memo entries ``(owner, name) -> value`` of a solver's potentials (module docstring).

    The owner is the potential itself (the contact pair potentials, friction) or an array the entry
    depends on (a Stable Neo-Hookean's ``tet_dFdx``, a Kirchhoff bending's ``hinges``: copies of the
    potential that share the array share the entry). Owners are held weakly: an owner's entries go
    when the owner goes, so the workspace extends no potential's life; values must not refer to
    their owner. :meth:`clear` drops everything (the solver does with its caches).
    """

    __slots__ = ("_entries", "__weakref__")

    def __init__(self) -> None:
        self._entries: dict[int, tuple[weakref.ref, dict[str, object]]] = {}

    def _names(self, owner: object, create: bool) -> dict[str, object] | None:
        """The entries of ``owner`` (created empty when ``create``), or None."""
        key = id(owner)
        slot = self._entries.get(key)
        if slot is not None and slot[0]() is owner:
            return slot[1]
        if not create:
            return None
        this = weakref.ref(self)

        def _drop(ref: weakref.ref) -> None:
            workspace = this()
            if workspace is not None and workspace._entries.get(key, (None,))[0] is ref:
                del workspace._entries[key]

        names: dict[str, object] = {}
        self._entries[key] = (weakref.ref(owner, _drop), names)
        return names

    def get(self, owner: object, name: str):
        """The entry ``name`` of ``owner``, or None."""
        names = self._names(owner, False)
        return None if names is None else names.get(name)

    def put(self, owner: object, name: str, value):
        """Keep ``value`` (not None) as the entry ``name`` of ``owner``, replacing the last one; returns ``value``."""
        self._names(owner, True)[name] = value
        return value

    def take(self, owner: object, name: str):
        """Remove and return the entry ``name`` of ``owner`` (None when there is none)."""
        names = self._names(owner, False)
        return None if names is None else names.pop(name, None)

    def clear(self) -> None:
        """Remove every entry."""
        self._entries.clear()

    def __len__(self) -> int:
        """The number of entries."""
        return sum(len(slot[1]) for slot in self._entries.values())

    def __reduce__(self):
        """A pickle or copy of a workspace is an empty one (the entries are only a memo)."""
        return (Workspace, ())


def workspace_of(potential) -> Workspace:
    """The workspace ``potential`` keeps its evaluations in: the one given to it (its ``workspace``
    attribute, set by the term that built it), else a private one created now."""
    workspace = potential.__dict__.get("workspace")
    if workspace is None:
        workspace = potential.workspace = Workspace()
    return workspace
