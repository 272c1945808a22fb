"""Launch the thinshell simulator node (``ros2 launch thinshell sim.launch.py [scene:=FILE] [mode:=...]``).

Parameters come from ``config/nodes/sim_node.yaml`` (installed under ``share/thinshell``), then the
launch arguments below override theirs. Needs a ROS 2 install with ``launch`` and ``launch_ros``;
the checks of tests/thinshell_ros/test_launch_files.py read this file without them.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    """The sim node with its parameter file and the ``scene``, ``mode``, ``backend``, ``record``,
    ``publish_image`` and ``use_sim_time`` arguments."""
    params_file = PathJoinSubstitution([FindPackageShare("thinshell"), "config", "nodes", "sim_node.yaml"])
    return LaunchDescription([
        DeclareLaunchArgument("scene", default_value="", description="scene file (empty: the bundled press_slide)"),
        DeclareLaunchArgument("mode", default_value="realtime", description="realtime | fast | stepped"),
        DeclareLaunchArgument("backend", default_value="auto", description="auto | numpy | taichi-cpu | taichi-cuda"),
        DeclareLaunchArgument("record", default_value="", description="bag directory to record into (empty: off)"),
        DeclareLaunchArgument("publish_image", default_value="false", description="render <sensor>/image"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="the node's clock from /clock"),
        Node(
            package="thinshell",
            executable="thinshell-sim-node",
            name="thinshell_sim",
            output="screen",
            parameters=[params_file, {
                "scene": LaunchConfiguration("scene"),
                "mode": LaunchConfiguration("mode"),
                "backend": LaunchConfiguration("backend"),
                "record": LaunchConfiguration("record"),
                "publish_image": LaunchConfiguration("publish_image"),
                "use_sim_time": LaunchConfiguration("use_sim_time"),
            }],
        ),
    ])
