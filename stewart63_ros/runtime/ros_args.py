"""The ROS arguments of a command line, split from a program's own options.

Every executable takes the standard ROS arguments after ``--ros-args``, up
to a ``--`` that closes them (or the end of the line); there may be several
such groups, as rcl allows. ``record`` and ``play`` hand them to
``rclpy.init`` and parse the rest themselves; the nodes read their
parameter files and ``-p`` overrides from them (``runtime/parameters.py``).
"""
from __future__ import annotations

from collections.abc import Sequence

#: Opens the ROS arguments; ``--`` closes them.
ROS_ARGS = '--ros-args'
END = '--'

#: ROS arguments that take a value (the next word, even one that starts with ``-``).
WITH_VALUE = frozenset({'-p', '--param', '--params-file', '-r', '--remap', '--log-level',
                        '--log-config-file', '-e', '--enclave', '--log-file-name'})


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a command line into the program's own words and the ROS arguments.

    Args:
        argv: the words of a command line, without the program's name.

    Returns:
        (own, ros): ``own`` the words outside every ``--ros-args ... [--]``
        group, in order; ``ros`` the words of every group, each group with
        its opening ``--ros-args`` and without the closing ``--`` (empty when
        the line has none), as ``rclpy.init(args=[prog] + ros)`` takes them.
    """
    own: list[str] = []
    ros: list[str] = []
    inside = False
    words = list(argv)
    i = 0
    while i < len(words):
        word = words[i]
        if word == ROS_ARGS:
            inside = True
            ros.append(word)
        elif not inside:
            own.append(word)
        elif word == END:
            inside = False
        else:
            ros.append(word)
            if word in WITH_VALUE and i + 1 < len(words):
                i += 1
                ros.append(words[i])
        i += 1
    return own, ros


def rclpy_args(prog: str, ros: Sequence[str]) -> list[str] | None:
    """What ``rclpy.init(args=...)`` takes for these ROS arguments (None: none given).

    Args:
        prog: the program's name (rcl reads the first word as it).
        ros: the ROS arguments, as ``split_ros_args`` returns them.
    """
    return [prog] + list(ros) if ros else None
