"""ros2 launch stewart63_ros rig_composed.launch.py [params_file:=F] [namespace:=NS]
    [clock_mode:=lockstep|realtime] [record:=DIR]

plant, controller and fk as nodes of ONE process (the ``composed``
executable, what ``rig --compose`` runs): each its own node with its own
name, parameters and /diagnostics, the traffic between them still on the
DDS topics, served by one loop (docs/running.md: "One process or several").
``record:=DIR`` adds the recorder to that process. Importing this file needs
no ROS package: the launch imports happen inside generate_launch_description().
"""


def default_params():
    """The packaged parameter file (installed share folder, or the checkout's).
    stewart63_ros.paths needs only the standard library: launch may run in a
    Python without this package's dependencies (numpy, scipy)."""
    from stewart63_ros.paths import default_params_path
    return str(default_params_path())


def _composed(context, *args, **kwargs):
    from launch.actions import EmitEvent, RegisterEventHandler
    from launch.event_handlers import OnProcessExit
    from launch.events import Shutdown
    from launch_ros.actions import Node

    def value(name):
        return context.launch_configurations[name]
    import tempfile

    import yaml
    arguments = ['--nodes', 'plant,controller,fk']
    record = value('record')
    if record:
        arguments += ['--record', record]
    # What rig decides, as a second parameter file after the user's: every
    # node reads its own section of both, as when it runs alone.
    shared = {'clock_mode': value('clock_mode'), 'wait_for_subscribers': 1 if record else 0}
    overlay = {'/**': {'ros__parameters': shared},
               '/**/plant': {'ros__parameters': dict(
                   shared, lengths_subscribers=3 if record else 2)}}
    with tempfile.NamedTemporaryFile('w', suffix='.yaml', prefix='stewart63_composed_',
                                     delete=False) as stream:
        yaml.safe_dump(overlay, stream, sort_keys=False)
    # No name=: it would rename every node of the process.
    node = Node(package='stewart63_ros', executable='composed', namespace=value('namespace'),
                output='screen', arguments=arguments,
                parameters=[value('params_file'), stream.name])
    # Like `rig`: when the process ends, end the launch.
    return [node, RegisterEventHandler(OnProcessExit(
        target_action=node, on_exit=[EmitEvent(event=Shutdown())]))]


def generate_launch_description():
    from launch.actions import DeclareLaunchArgument, OpaqueFunction

    from launch import LaunchDescription
    from stewart63_ros.paths import RIG_CLOCK_MODE

    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params()),
        DeclareLaunchArgument('namespace', default_value=''),
        DeclareLaunchArgument('clock_mode', default_value=RIG_CLOCK_MODE),
        DeclareLaunchArgument('record', default_value=''),
        OpaqueFunction(function=_composed)])
