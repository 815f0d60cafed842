"""Launch the dtm_labeler node (full ROS 2 installs; launch/launch_ros are not on PyPI).

    ros2 launch dtm_labeler labeler.launch.py model_path:=/path/model.npz
    ros2 launch dtm_labeler labeler.launch.py params_file:=/path/my_params.yaml namespace:=mocap
    ros2 launch dtm_labeler labeler.launch.py model_path:=/path/model.npz \
        input_type:=mocap4r2_markers input_topic:=/markers managed:=true

The parameters file (default: the package's params/labeler.yaml, keyed ``/**`` so it applies in
any namespace) is loaded first. Only the arguments given on the command line override it:
``model_path`` when not empty, ``input_type`` when not empty, ``use_sim_time`` when given.
``input_topic`` remaps ``markers/unlabeled`` (e.g. ``/markers`` of a mocap4r2 driver,
``pointCloud`` of motion_capture_tracking). ``managed:=true`` starts the lifecycle node
(``labeler_lifecycle_node``): configure and activate it with ``ros2 lifecycle set``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _node(context):
    def arg(name):
        return LaunchConfiguration(name).perform(context)

    overrides = {}
    if arg("model_path"):
        overrides["model_path"] = arg("model_path")
    if arg("input_type"):
        overrides["input_type"] = arg("input_type")
    if arg("use_sim_time"):
        overrides["use_sim_time"] = arg("use_sim_time").lower() in ("true", "1", "yes")
    params = [arg("params_file")] + ([overrides] if overrides else [])
    remaps = [("markers/unlabeled", arg("input_topic"))] if arg("input_topic") else []
    managed = arg("managed").lower() in ("true", "1", "yes")
    return [Node(
        package="dtm_labeler",
        executable="labeler_lifecycle_node" if managed else "labeler_node",
        name="dtm_labeler",
        namespace=arg("namespace"),
        output="screen",
        emulate_tty=True,
        parameters=params,
        remappings=remaps,
        arguments=["--ros-args", "--log-level", arg("log_level")],
    )]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("dtm_labeler"), "params", "labeler.yaml")
    args = [
        ("model_path", "", "Model file (.npz from dtm-train); empty = the params file's model_path"),
        ("params_file", default_params, "ROS 2 parameters file for the node"),
        ("namespace", "", "Namespace of the node and its topics"),
        ("input_type", "", "pointcloud2 | mocap4r2_markers | pointcloud; empty = the params file's"),
        ("input_topic", "", "Topic the unlabeled markers come on (remaps markers/unlabeled); empty = no remap"),
        ("use_sim_time", "", "true to use /clock (e.g. with ros2 bag play --clock); empty = the params file's"),
        ("managed", "false", "true: start the lifecycle (managed) node"),
        ("log_level", "info", "Logger level"),
    ]
    return LaunchDescription([DeclareLaunchArgument(n, default_value=d, description=t) for n, d, t in args]
                             + [OpaqueFunction(function=_node)])
