"""Launch the thinshell recorder (``ros2 launch thinshell record.launch.py out:=DIR [scene:=FILE]``).

Runs ``thinshell record --out DIR --namespace NS --scene FILE`` (:func:`thinshell_ros.recorder.record_main`:
every INTERFACES.md topic under the namespace and ``/clock``, until the launch is stopped). The
recorder has no ROS parameters besides ``use_sim_time`` (log times from ``/clock``). Needs a ROS 2
install with ``launch`` and ``launch_ros``; the checks of tests/thinshell_ros/test_launch_files.py
read this file without them.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    """The recorder with the ``out``, ``namespace``, ``scene`` and ``use_sim_time`` arguments."""
    return LaunchDescription([
        DeclareLaunchArgument("out", description="bag directory to create"),
        DeclareLaunchArgument("namespace", default_value="/thinshell", description="namespace of the topics"),
        DeclareLaunchArgument("scene", default_value="", description="scene file copied into the bag"),
        DeclareLaunchArgument("use_sim_time", default_value="true", description="log times from /clock"),
        Node(
            package="thinshell",
            executable="thinshell",
            name="thinshell_recorder",
            output="screen",
            arguments=["record", "--out", LaunchConfiguration("out"), "--namespace", LaunchConfiguration("namespace"),
                       "--scene", LaunchConfiguration("scene")],
            parameters=[{"use_sim_time": LaunchConfiguration("use_sim_time")}],
        ),
    ])
