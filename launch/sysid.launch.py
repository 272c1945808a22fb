"""Launch the thinshell sysid node (``ros2 launch thinshell sysid.launch.py bag:=DIR [apply_to:=/thinshell_sim]``).

Parameters come from ``config/nodes/sysid_node.yaml`` (installed under ``share/thinshell``), then the
launch arguments below override theirs; a fit starts on ``ros2 service call /thinshell_sysid/fit
std_srvs/srv/Trigger``. Needs a ROS 2 install with ``launch`` and ``launch_ros``; the checks of
tests/thinshell_ros/test_launch_files.py read this file without them.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    """The sysid node with its parameter file and the ``bag``, ``params``, ``out``, ``apply_to`` and
    ``recording_map`` arguments."""
    params_file = PathJoinSubstitution([FindPackageShare("thinshell"), "config", "nodes", "sysid_node.yaml"])
    return LaunchDescription([
        DeclareLaunchArgument("bag", default_value="", description="recording to fit (rosbag2 directory)"),
        DeclareLaunchArgument("params", default_value="", description="comma-separated parameters (empty: defaults)"),
        DeclareLaunchArgument("out", default_value="", description="report directory (empty: a new one)"),
        DeclareLaunchArgument("apply_to", default_value="", description="sim node to set the fitted values on"),
        DeclareLaunchArgument("recording_map", default_value="",
                              description="a real cell's recording map (empty: the bag's recording.yaml, if any)"),
        Node(
            package="thinshell",
            executable="thinshell-sysid-node",
            name="thinshell_sysid",
            output="screen",
            parameters=[params_file, {
                "bag": LaunchConfiguration("bag"),
                "params": LaunchConfiguration("params"),
                "out": LaunchConfiguration("out"),
                "apply_to": LaunchConfiguration("apply_to"),
                "recording_map": LaunchConfiguration("recording_map"),
            }],
        ),
    ])
