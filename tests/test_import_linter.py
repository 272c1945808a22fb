"""The import contracts of ``.importlinter`` (layers thinshell_ros -> sysid -> sim_core, no ROS or bag
library in sim_core, bags read only in sysid.bagio, no cycles between sibling modules, the shared Taichi
infrastructure free of energies, the energies' NumPy references free of Taichi), checked with
import-linter's ``lint-imports`` so that ``make test`` and CI check them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint(config: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", str(config)], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120, check=False)


def test_lint_imports_is_installed():
    assert LINT_IMPORTS.is_file(), f"{LINT_IMPORTS} missing: pip install -r requirements.txt (import-linter)"


def test_the_import_contracts_are_kept():
    run = _lint(REPO / ".importlinter")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "0 broken" in run.stdout and "BROKEN" not in run.stdout


def test_a_broken_contract_fails(tmp_path):
    """The check can fail: sim_core does import numpy, and a contract forbidding it is reported broken."""
    config = tmp_path / "broken.ini"
    config.write_text("[importlinter]\nroot_packages =\n    sim_core\ninclude_external_packages = True\n\n"
                      "[importlinter:contract:numpy]\nname = sim_core without numpy\ntype = forbidden\n"
                      "source_modules =\n    sim_core\nforbidden_modules =\n    numpy\n")
    run = _lint(config)
    assert run.returncode != 0 and "sim_core without numpy BROKEN" in run.stdout
