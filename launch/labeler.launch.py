"""Launch the dtm_labeler node (full ROS 2 installs; launch/launch_ros are not on PyPI).

    ros2 launch dtm_labeler labeler.launch.py model_path:=/path/model.npz
    ros2 launch dtm_labeler labeler.launch.py model_path:=/path/model.npz \
        params_file:=/path/my_params.yaml namespace:=mocap use_sim_time:=true

The parameters file (default: the package's params/labeler.yaml, every parameter with its
default) is loaded first; model_path (and use_sim_time) given here override it.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("dtm_labeler"), "params", "labeler.yaml")
    model_path = LaunchConfiguration("model_path")
    params_file = LaunchConfiguration("params_file")
    namespace = LaunchConfiguration("namespace")
    use_sim_time = LaunchConfiguration("use_sim_time")
    log_level = LaunchConfiguration("log_level")
    return LaunchDescription([
        DeclareLaunchArgument("model_path", default_value="",
                              description="Model file (.npz from dtm-train); empty = start without a model"),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 parameters file for the node"),
        DeclareLaunchArgument("namespace", default_value="", description="Namespace of the node and its topics"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="Use /clock (e.g. with ros2 bag play --clock)"),
        DeclareLaunchArgument("log_level", default_value="info", description="Logger level"),
        Node(
            package="dtm_labeler",
            executable="labeler_node",
            name="dtm_labeler",
            namespace=namespace,
            output="screen",
            emulate_tty=True,
            parameters=[params_file, {"model_path": ParameterValue(model_path, value_type=str),
                                     "use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
            arguments=["--ros-args", "--log-level", log_level],
        ),
    ])
