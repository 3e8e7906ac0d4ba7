# SPDX-License-Identifier: Apache-2.0
"""RViz for launch/lompr.launch.xml (rviz:=true): robot_state_publisher on kinematics_node's
full joint state and rviz2 with rviz/lompr.rviz, each given the site's frame prefix and URDF
(`lompr_predictor.ros.launch_site`), which XML cannot read out of the params file."""

from __future__ import annotations

from pathlib import Path

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from lompr_predictor.ros.launch_site import view_settings

PACKAGE = 'lompr_predictor'
#: Arguments and their defaults (empty: not given), as lompr.launch.xml passes them.
ARGUMENTS = {'namespace': '', 'params_file': '', 'use_sim_time': 'false',
             'robot_description_file': '', 'frame_prefix': ''}


def viewers(context: LaunchContext) -> list[Node]:
    """robot_state_publisher and rviz2, their settings resolved now the arguments are."""
    given = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    share = Path(FindPackageShare(PACKAGE).perform(context))
    settings = view_settings(given['params_file'], given['namespace'],
                             given['robot_description_file'],
                             given['frame_prefix'], share / 'description' / 'lompr.urdf')
    sim_time = given['use_sim_time'].lower() == 'true'
    return [
        Node(package='robot_state_publisher', executable='robot_state_publisher',
             name='robot_state_publisher', namespace=given['namespace'], output='screen',
             parameters=[{'robot_description': settings.robot_description,
                          'frame_prefix': settings.frame_prefix, 'use_sim_time': sim_time}],
             remappings=[('joint_states', 'lompr/full_joint_states')]),
        Node(package='rviz2', executable='rviz2', name='rviz2', namespace=given['namespace'],
             arguments=['-d', str(share / 'rviz' / 'lompr.rviz'), '-f', settings.fixed_frame],
             parameters=[{'use_sim_time': sim_time}]),
    ]


def generate_launch_description() -> LaunchDescription:
    """The arguments, then the two nodes."""
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default)
          for name, default in ARGUMENTS.items()),
        OpaqueFunction(function=viewers)])
