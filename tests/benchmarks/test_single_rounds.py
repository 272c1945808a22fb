"""The single-environment rounds' summary (benchmarks/single_rounds.py): medians per tree and arch, the per-round
arch and tree ratios, and the refusal of runs whose Newton iterations differ."""

from __future__ import annotations

import pytest

from benchmarks.single_rounds import _summary, main


def _records(rates: dict[tuple[str, str], list[list[float]]], iterations: float = 4.9388) -> list[dict]:
    """Run records of ``rates[tree, arch][round][run]`` steps/s."""
    return [{"tree": tree, "arch": arch, "round": k + 1, "run": n + 1, "steps_per_s": rate,
             "newton_iters_mean": iterations}
            for (tree, arch), rounds in rates.items() for k, runs in enumerate(rounds) for n, rate in enumerate(runs)]


def test_summary_gives_per_round_ratios_of_round_medians(capsys):
    records = _records({("main", "cuda"): [[20.0, 22.0, 24.0], [30.0, 33.0, 36.0]],
                        ("main", "cpu"): [[10.0, 11.0, 12.0], [30.0, 30.0, 30.0]],
                        ("br", "cuda"): [[22.0, 22.0, 22.0], [36.3, 36.3, 36.3]],
                        ("br", "cpu"): [[11.0, 11.0, 11.0], [30.0, 30.0, 30.0]]})
    assert _summary(records, ["main", "br"], ["cuda", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "main: cuda / cpu steps/s, per round: 2.000 1.100; median 1.550 (1.100-2.000)" in out
    assert "cuda: br / main steps/s, per round: 1.000 1.100; median 1.050 (1.000-1.100)" in out
    assert "main         cuda      6      27.00 (20.00-36.00)  22.00 33.00" in out


def test_summary_splits_the_step_into_linear_solve_and_rest(capsys):
    records = _records({("main", "cuda"): [[20.0, 25.0]]})
    for r, share in zip(records, (0.5, 0.6)):
        r.update(forward_total_s=1.0, linear_solve_share=share)
    assert _summary(records, ["main"], ["cuda"]) == 0
    assert "ms a step: 45.00 (40.00-50.00), of which the linear solve 24.50 (24.00-25.00) and the rest 20.50 " \
           "(16.00-25.00)" in capsys.readouterr().out


def test_summary_fails_when_iterations_differ(capsys):
    records = _records({("main", "cuda"): [[20.0]]}) + _records({("main", "cpu"): [[20.0]]}, iterations=5.0)
    assert _summary(records, ["main"], ["cuda", "cpu"]) == 1
    assert "Newton iterations per step differ" in capsys.readouterr().out


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit):
        main(["--rounds", "0"])
    with pytest.raises(SystemExit):
        main(["--trees", "nodir"])
