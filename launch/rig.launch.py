"""ros2 launch stewart63_ros rig.launch.py [params_file:=F] [namespace:=NS]
                                          [clock_mode:=lockstep|realtime]

The same three processes as the `rig` executable (plant, controller, fk), for
ROS 2 installs that have `launch`. Recording: `ros2 bag record` or our
`record`, see docs/running.md. Importing this file needs no ROS package: the launch
imports happen inside generate_launch_description().
"""


def default_params():
    """The packaged parameter file (installed share folder, or the checkout's).
    stewart63_ros.paths needs only the standard library: launch may run in a
    Python without this package's dependencies (numpy, scipy)."""
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
        DeclareLaunchArgument('clock_mode', default_value=RIG_CLOCK_MODE),
        *nodes, *handlers])
