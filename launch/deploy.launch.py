"""Launch the thinshell deploy node (``ros2 launch thinshell deploy.launch.py trajectory:=FILE``).

Parameters come from a cell's copy of ``config/nodes/deploy_node.yaml`` (``params_file``; default the
installed template, whose values marked MEASURE are placeholders: docs/deploy.md), then the
launch arguments below override theirs. The node plays the trajectory once and exits (0 when it
completed). Needs a ROS 2 install with ``launch`` and ``launch_ros``; the checks of
tests/thinshell_ros/test_launch_files.py read this file without them.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    """The deploy node with a cell's parameter file and the ``trajectory`` and ``dry_run`` arguments."""
    template = PathJoinSubstitution([FindPackageShare("thinshell"), "config", "nodes", "deploy_node.yaml"])
    return LaunchDescription([
        DeclareLaunchArgument("trajectory", description="trajectory.yaml (or a bag directory) to play"),
        DeclareLaunchArgument("params_file", default_value=template,
                              description="the cell's copy of config/nodes/deploy_node.yaml"),
        DeclareLaunchArgument("dry_run", default_value="false", description="check and plan only, publish nothing"),
        Node(
            package="thinshell",
            executable="thinshell-deploy-node",
            name="thinshell_deploy",
            output="screen",
            parameters=[LaunchConfiguration("params_file"), {
                "trajectory": LaunchConfiguration("trajectory"),
                "dry_run": LaunchConfiguration("dry_run"),
            }],
        ),
    ])
