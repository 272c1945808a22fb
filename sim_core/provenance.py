"""Where a result came from: the git revision of the thinshell checkout that produced it.

``thinshell optimise`` (:mod:`sim_core.optim.cli`) writes it into its trajectory files and
``thinshell sysid`` (:mod:`sysid.results`) into ``fit.json``'s provenance.
"""

from __future__ import annotations

import subprocess
from pathlib import Path


def git_revision(repo: Path | None = None) -> tuple[str | None, bool | None]:
    """``(commit hash, working tree dirty)`` of the thinshell checkout, ``(None, None)`` outside git."""
    repo = repo or Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10)
        if rev.returncode != 0:
            return None, None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, timeout=10)
        return rev.stdout.strip(), bool(dirty.stdout.strip()) if dirty.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None, None
