"""The Coulomb friction coefficients of a model's contacts: between the bodies of two vertices and between a body and
an obstacle (:meth:`sim_core.model.Model.friction_coefficient`), kept while ``model.friction`` is unchanged (a
generated effect may edit it between steps)."""

from __future__ import annotations

import numpy as np

from sim_core.model import Model


class CoulombCoefficients:
    """Coulomb coefficients (dimensionless) of a model's body pairs and body-obstacle pairs.

    Args:
        model: the model (its ``friction`` table is read again whenever it has changed).
        body_names: the bodies in the order of ``vertex_body``'s indices, ``(b,)``.
        vertex_body: the body index of each vertex, int ``(n,)``.
    """

    def __init__(self, model: Model, body_names: list[str], vertex_body: np.ndarray) -> None:
        self.model = model
        self.body_names = body_names
        self.vertex_body = vertex_body
        self._table: tuple | None = None  # (model.friction's items, (b, b) table)
        self._obstacles: dict[str, np.ndarray] = {}

    def between(self, vertex_a: np.ndarray, vertex_b: np.ndarray) -> np.ndarray:
        """Coulomb coefficients ``(p,)`` between the bodies of vertices ``vertex_a`` and ``vertex_b`` ``(p,)``."""
        return self.table()[self.vertex_body[vertex_a], self.vertex_body[vertex_b]]

    def table(self) -> np.ndarray:
        """Coulomb coefficients between the bodies ``(b, b)``, built again only when ``model.friction`` has
        changed."""
        key = tuple(self.model.friction.items())
        kept = self._table
        if kept is None or kept[0] != key:
            names = self.body_names
            table = np.array([[self.model.friction_coefficient(a, b) for b in names] for a in names],
                             dtype=float).reshape(len(names), len(names))
            kept = self._table = (key, table)
            self._obstacles = {}
        return kept[1]

    def obstacle(self, name: str) -> np.ndarray:
        """Coulomb coefficients ``(b,)`` between each body and the obstacle (plane or sphere) ``name``, kept while
        ``model.friction`` is unchanged."""
        self.table()  # forgets the kept columns when model.friction has changed
        column = self._obstacles.get(name)
        if column is None:
            column = self._obstacles[name] = np.array(
                [self.model.friction_coefficient(b, name) for b in self.body_names], dtype=float)
        return column
