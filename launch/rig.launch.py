"""ros2 launch stewart63_ros rig.launch.py [params_file:=F] [namespace:=NS]
                                          [clock_mode:=lockstep|realtime]

The same three processes as the `rig` executable (plant, controller, fk), for
ROS 2 installs that have `launch`. Recording: `ros2 bag record` or our
`record`, see README. Importing this file needs no ROS package: the launch
imports happen inside generate_launch_description().
"""
import os


def default_params():
    try:
        from ament_index_python.packages import get_package_share_directory
        return os.path.join(get_package_share_directory('stewart63_ros'), 'config',
                            'stewart63.yaml')
    except Exception:  # noqa: BLE001 - a checkout without an install
        return os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                            'config', 'stewart63.yaml')


def generate_launch_description():
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, RegisterEventHandler, Shutdown
    from launch.event_handlers import OnProcessExit
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    params = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    clock_mode = LaunchConfiguration('clock_mode')
    common = [params, {'clock_mode': clock_mode}]
    controller = Node(package='stewart63_ros', executable='controller', name='controller',
                      namespace=namespace, parameters=common, output='screen')
    fk = Node(package='stewart63_ros', executable='fk', name='fk', namespace=namespace,
              parameters=common, output='screen')
    plant = Node(package='stewart63_ros', executable='plant', name='plant',
                 namespace=namespace, output='screen',
                 parameters=common + [{'lengths_subscribers': 2}])
    nodes = [plant, controller, fk]
    # Like `rig`: when any node ends, end the launch (a dead node fails the rig).
    handlers = [RegisterEventHandler(OnProcessExit(target_action=node, on_exit=[Shutdown()]))
                for node in nodes]
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params()),
        DeclareLaunchArgument('namespace', default_value=''),
        DeclareLaunchArgument('clock_mode', default_value='lockstep'),
        *nodes, *handlers])
