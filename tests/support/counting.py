"""Counting the objects a class makes, to test what a constructor or a step builds (``monkeypatch`` fixture)."""

from __future__ import annotations


def counting(monkeypatch, module, name: str) -> list:
    """Replace the class ``module.name`` by a subclass that appends each instance it makes to the returned list
    (undone with ``monkeypatch`` at the test's end)."""
    made: list = []
    base = getattr(module, name)

    class Counted(base):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(module, name, Counted)
    return made
