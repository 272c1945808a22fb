"""The README's and docs' relative links point at files of the tree, and every command the README's
table names is a subcommand of the CLI (or a console script of setup.py)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_relative_links_resolve(doc):
    missing = [target for target in LINK.findall(doc.read_text(encoding="utf-8"))
               if "://" not in target and not (doc.parent / target).exists()]
    assert not missing, f"{doc.relative_to(REPO)}: links to missing files {missing}"


def test_the_readme_command_table_names_real_commands():
    from thinshell_ros.cli import COMMANDS

    subcommands = set(COMMANDS)
    scripts = set(re.findall(r"\"(thinshell-[a-z-]+)\s*=", (REPO / "setup.py").read_text(encoding="utf-8")))
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    table = readme.split("## Commands", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|")[1] for line in table.splitlines() if line.startswith("| `")]
    named = {w for row in rows for w in re.findall(r"`(thinshell[- ][a-z-]+)", row)}
    assert named, "the README has no command table"
    for name in named:
        if name.startswith("thinshell-"):
            assert name in scripts, f"README names {name}, not a console script of setup.py"
        else:
            assert name.split()[1] in subcommands, f"README names {name}, not a `thinshell` subcommand"
