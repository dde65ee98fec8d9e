"""ros2 launch stewart63_ros rig_bus.launch.py [params_file:=F] [namespace:=NS]
                                              [clock_mode:=lockstep|realtime]
                                              [bus_config:=F]

The rig with the plant on the field bus (what `rig --bus canopen` runs):
plant (``io: canopen``, the legs' CiA 402 drives), canopen_bridge (the
master of the bus, publishing ``leg_lengths``), controller and fk; see
docs/bus.md. Importing this file needs no ROS package: the launch imports
happen inside generate_launch_description().
"""


def default_params():
    """The packaged parameter file (standard library only, see rig.launch.py)."""
    from stewart63_ros.paths import default_params_path
    return str(default_params_path())


def generate_launch_description():
    from launch.actions import DeclareLaunchArgument, RegisterEventHandler, Shutdown
    from launch.event_handlers import OnProcessExit
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    from launch import LaunchDescription
    from stewart63_ros.paths import RIG_CLOCK_MODE

    params = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    clock_mode = LaunchConfiguration('clock_mode')
    bus = {'bus_config': LaunchConfiguration('bus_config')}
    common = [params, {'clock_mode': clock_mode}]
    controller = Node(package='stewart63_ros', executable='controller', name='controller',
                      namespace=namespace, parameters=common, output='screen')
    fk = Node(package='stewart63_ros', executable='fk', name='fk', namespace=namespace,
              parameters=common, output='screen')
    bridge = Node(package='stewart63_ros', executable='canopen_bridge', name='canopen_bridge',
                  namespace=namespace, output='screen',
                  parameters=common + [bus, {'lengths_subscribers': 2}])
    plant = Node(package='stewart63_ros', executable='plant', name='plant',
                 namespace=namespace, output='screen',
                 parameters=common + [bus, {'io': 'canopen'}])
    nodes = [plant, bridge, controller, fk]
    # Like `rig`: when any node ends, end the launch (a dead node fails the rig).
    handlers = [RegisterEventHandler(OnProcessExit(target_action=node, on_exit=[Shutdown()]))
                for node in nodes]
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params()),
        DeclareLaunchArgument('namespace', default_value=''),
        DeclareLaunchArgument('clock_mode', default_value=RIG_CLOCK_MODE),
        DeclareLaunchArgument('bus_config', default_value=''),
        *nodes, *handlers])
