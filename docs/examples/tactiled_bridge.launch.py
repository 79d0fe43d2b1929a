"""ros2 launch docs/examples/tactiled_bridge.launch.py: the ROS 2 bridge of one fingertip under /robot1.

tactiled is a pip package, not an ament one, so the bridge runs as a process (ExecuteProcess), with
the same --ros-args a ROS node takes: namespace, remapping and parameters.
"""
from launch import LaunchDescription
from launch.actions import ExecuteProcess

CMD = ["tactiled", "ros2", "--connect", "tcp://127.0.0.1:7350", "--ros-args",
       "-r", "__ns:=/robot1", "-r", "__node:=fingertip_bridge",
       "-p", "sensor_id:=fingertip0", "-p", "frame_id:=fingertip_link"]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([ExecuteProcess(cmd=CMD, output="screen")])
