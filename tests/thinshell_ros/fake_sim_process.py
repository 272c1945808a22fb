"""The sim node with the kinematic FakeSimulation in a process of its own (DDS tests of timing).

``python -m tests.thinshell_ros.fake_sim_process --ros-args -p mode:=realtime``: as a robot cell,
the sim node does not share the test's Python interpreter (nor its executor) with the node under test.
"""

from __future__ import annotations

import sys

from tests.thinshell_ros.fake_sim import FakeSimulation
from thinshell_ros.runtime import ros_session, spin_until_stopped
from thinshell_ros.sim_node import SimNode


def main() -> int:
    """Run the sim node around a FakeSimulation until SIGINT/SIGTERM."""
    with ros_session(sys.argv) as stop:
        node = SimNode(sim=FakeSimulation())
        try:
            spin_until_stopped(node, stop)
        finally:
            node.destroy_node()
    return 0


if __name__ == "__main__":
    sys.exit(main())
