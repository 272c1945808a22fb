"""Entry point of ``thinshell diagnose`` for the CLI dispatcher (re-export of :func:`sysid.diagnose.cli.diagnose_main`)."""

from __future__ import annotations

from sysid.diagnose.cli import diagnose_main

__all__ = ["diagnose_main"]
