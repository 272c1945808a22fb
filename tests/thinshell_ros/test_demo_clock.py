"""``thinshell demo``'s stage clock (thinshell_ros.demo_clock): a ``thinshell`` tool run in the background
gives its exit code, its log, and the CPU seconds the kernel accounts to it."""

from __future__ import annotations

import time

import pytest

from thinshell_ros.demo_clock import BackgroundTool, Phase, cpu_seconds


def test_a_background_tools_cpu_seconds_are_those_the_kernel_accounts_to_it_when_reaped(tmp_path):
    # `thinshell compare --help` imports the replay stack (numpy, Taichi, ...): a second of CPU or so
    phase = Phase("compare", ("compare",))
    before = cpu_seconds()
    tool = BackgroundTool("compare", ["--help"], tmp_path / "compare.log")
    tool._watch.join()                                    # the tool has exited (not reaped yet) ...
    time.sleep(0.5)
    waited = time.monotonic() - tool._t0
    assert tool.wait() == 0 and tool.wait() == 0          # a second wait returns the same code
    assert tool.wall_s <= waited - 0.5                    # ... its wall time ends at its exit, not at the wait
    reaped = cpu_seconds() - before
    phase.stop()
    assert tool.cpu_s is not None and tool.cpu_s > 0.05, tool.cpu_s
    # read from /proc before the child was reaped: the same user + system time getrusage then adds to
    # RUSAGE_CHILDREN (to the clock tick), and the phase's CPU holds it
    assert tool.cpu_s == pytest.approx(reaped, abs=0.03)
    assert phase.cpu_s >= tool.cpu_s - 0.03 and phase.wall_s >= tool.wall_s > 0
    assert "usage: thinshell compare" in tool.log_tail() and tool.command == "thinshell compare --help"
    assert phase.as_dict()["stages"] == ["compare"]


def test_a_failing_background_tool_gives_its_exit_code_and_its_reason_in_the_log(tmp_path):
    missing = tmp_path / "no_such_bag"
    tool = BackgroundTool("diagnose", [missing, "--json", tmp_path / "d.json"], tmp_path / "diagnose.log")
    assert tool.wait() != 0
    assert str(missing) in tool.log_tail()
    tool.stop()                                            # ended already: nothing to do
    assert not (tmp_path / "d.json").exists()
