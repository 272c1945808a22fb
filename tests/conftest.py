"""Suite-wide collection order: modules marked ``early`` first (see pytest.ini's ``early`` marker).

``make test`` runs the suite in two pytest-xdist workers with ``--dist loadfile
--no-loadscope-reorder``: each test module goes to one worker whole (its module-scoped fixtures are
built once), and the modules are handed out in collection order, each to the next free worker. A
module that takes minutes (the full ``thinshell diagnose`` runs) collected late would start when
the other worker has little left to do and run alone at the end; collected first, it runs beside
the rest of the suite. A serial run is unaffected apart from the order.
"""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Move the items of modules marked ``early`` to the front; the order is otherwise kept (stable)."""
    items[:] = sorted(items, key=lambda item: item.get_closest_marker("early") is None)
