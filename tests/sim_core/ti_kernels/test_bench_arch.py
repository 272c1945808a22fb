"""``thinshell bench --arch``: cpu runs the Taichi kernels, numpy the reference, bad archs exit 2."""

from __future__ import annotations

import json

from thinshell_ros.bench import bench_main


def test_forming_on_taichi_cpu_prints_one_json_line(ti_cpu, capsys):
    assert bench_main(["forming", "--arch", "cpu", "--steps", "1", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1  # Taichi's banner and start-up line stay off stdout
    r = json.loads(lines[0])
    assert r["arch"] == "cpu" and r["dofs"] == 1698
    assert r["backend"] == "taichi-cpu"  # what the sim node runs with backend taichi-cpu (or auto here)
    assert r["taichi_terms"] == []  # no potential swapped for a Taichi twin: the fused kernels evaluate them


def test_unknown_or_unavailable_arch_exits_2(ti_cpu, capsys):
    assert bench_main(["forming", "--arch", "metal", "--steps", "1"]) == 2
    assert "--arch metal: unknown backend" in capsys.readouterr().err
    # this process already runs Taichi on the CPU, so cuda is refused with the reason
    assert bench_main(["forming", "--arch", "cuda", "--steps", "1"]) == 2
    assert "--arch cuda: init_backend: Taichi is already initialised" in capsys.readouterr().err
