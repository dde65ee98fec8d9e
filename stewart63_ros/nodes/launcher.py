"""Starting and stopping a node process: options, rclpy, signals, exit codes."""
from __future__ import annotations

import argparse
import signal
import sys
import time

from stewart63_ros.nodes.realtime import reduce_timer_slack


def make_parser(prog: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        epilog='ROS arguments follow --ros-args, e.g. --ros-args --params-file '
        'config/stewart63.yaml -r __ns:=/rig2 -p name:=value (docs/interface.md).')
    return parser


def _interrupt(*_):
    raise KeyboardInterrupt


def run(prog: str, description: str, node_class, argv=None, extra_args=None) -> int:
    """Parse --help / own options, start rclpy, run the node until shutdown.

    Exits 2 with a one-line message on a parameter error; SIGTERM and Ctrl-C
    stop the node cleanly.
    """
    from stewart63_ros.core.params import ParameterError
    argv = list(sys.argv if argv is None else argv)
    parser = make_parser(prog, description)
    if extra_args:
        extra_args(parser)
    import rclpy
    from rclpy.utilities import remove_ros_args
    options = parser.parse_args(remove_ros_args(argv)[1:])
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions
    reduce_timer_slack()
    # Our own handlers: Ctrl-C and SIGTERM raise KeyboardInterrupt, so the
    # node flushes its last messages to the recorder before rclpy shuts down.
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    # SIGTERM (from rig, systemd, docker) ends the node like Ctrl-C does.
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    node = None
    code = 0
    try:
        node = node_class(options)
        code = node.run() or 0
    except ParameterError as exc:
        print('%s: parameter error: %s' % (prog, exc), file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        if node is not None:
            started = time.monotonic()
            try:
                node.close()
            except Exception as exc:  # noqa: BLE001 - shutting down anyway: say why, go on
                print('%s: while closing: %s' % (prog, exc), file=sys.stderr)
            node.destroy_node()
            # In the node's log, so that a slow stop shows where it went.
            print('%s: stopped (exit %d, close took %.2f s)'
                  % (prog, code, time.monotonic() - started), flush=True)
        if rclpy.ok():
            rclpy.shutdown()
    return code
