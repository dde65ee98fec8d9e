"""``fk``: the forward-kinematics node, or one solution without DDS.

    fk [--ros-args ...]                                       the node (nodes/fk_node.py)
    fk --solve L1 .. L6 [--params FILE] [--all] [--strict]    print JSON (tools/fk_solve.py)

The console script dispatches here, so that the node knows nothing of the
tool and the tool nothing of ROS.
"""
from __future__ import annotations

import sys

from stewart63_ros.runtime.ros_args import split_ros_args
from stewart63_ros.tools.cli import quiet_on_closed_pipe


@quiet_on_closed_pipe
def main(argv=None):
    """Run the solver when ``--solve`` is among the arguments, else the node.

    Args:
        argv: the whole command line, program name first (default ``sys.argv``).
    """
    argv = list(sys.argv if argv is None else argv)
    if '--solve' in split_ros_args(argv[1:])[0]:
        # lazy: fk_solve costs 865 ms; the node runs without it
        from stewart63_ros.tools.fk_solve import main as solve
        sys.exit(solve(argv[1:]))
    # lazy: fk_node costs 988 ms; fk --solve needs no ROS
    from stewart63_ros.nodes.fk_node import main as node
    from stewart63_ros.tools.fk_solve import add_solve_options
    node(argv, extra_args=add_solve_options)


if __name__ == '__main__':
    main()
