"""``fk --solve L1 .. L6``: the platform pose from six leg lengths, as JSON, without DDS.

Prints the assembly mode nearest the parameter file's initial pose, or with
``--all`` every real assembly mode (nearest first). Each pose carries
position [m], theta [rad] (R = Rz Ry Rx, docs/interface.md), quaternion
(x, y, z, w), the Jacobian's condition number and whether it is flagged as
near-singular. Lengths outside the stroke [leg_length_min, leg_length_max]
are named in ``outside_stroke`` beside the pose (and on stderr). Exit status
2 with a one-line reason on stderr when the lengths admit no assembly or the
parameter file is unusable.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

from stewart63_ros.core.mechanics.fk import ForwardKinematics, NoAssemblyError
from stewart63_ros.tools.cli import STRICT_HELP, announce_compile, load_checked


def _length(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError('not a number: %r' % text) from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError('not a finite number: %r' % text)
    return value


def _pose(mode) -> dict:
    return {
        'position': [float(v) for v in mode.position],
        'theta': [float(v) for v in mode.theta],
        'quaternion': [float(v) for v in mode.quaternion],
        'condition_number': float(mode.condition),
        'singular': bool(mode.singular),
        'residual': float(mode.residual),
    }


def add_solve_options(parser: argparse.ArgumentParser) -> None:
    """The ``--solve`` options, as the node's ``fk --help`` lists them."""
    parser.add_argument('--solve', nargs=6, metavar='L', type=float,
                        help='solve once for six leg lengths and print JSON (no DDS)')
    parser.add_argument('--params', metavar='FILE', help='with --solve: parameter file')
    parser.add_argument('--all', action='store_true', help='with --solve: every assembly mode')
    parser.add_argument('--strict', action='store_true', help='with --solve: ' + STRICT_HELP)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='fk', description='Forward kinematics of the platform (a 6-3 or a 6-6) from six '
        'leg lengths (no ROS needed). Prints JSON on stdout.')
    parser.add_argument('--solve', nargs=6, type=_length, required=True, metavar='L',
                        help='the six leg lengths L1 .. L6 [m]')
    parser.add_argument('--params', metavar='FILE', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    parser.add_argument('--all', action='store_true',
                        help='print every assembly mode, nearest the initial pose first')
    parser.add_argument('--strict', action='store_true', help=STRICT_HELP)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    setup = load_checked('fk', args.params, node_name='fk', strict=args.strict)
    if setup is None:
        return 2
    mech = setup.mechanism
    announce_compile('fk')
    try:
        modes = ForwardKinematics(mech, start=(setup.task.initial_position,
                                               setup.task.initial_rotation)).all_modes(args.solve)
    except NoAssemblyError as exc:
        print('fk: no assembly: %s' % exc, file=sys.stderr)
        return 2
    outside = ['leg_%d: %.6g m is outside the stroke [%g, %g]' % (
        i + 1, value, mech.leg_length_min, mech.leg_length_max)
        for i, value in enumerate(args.solve)
        if not mech.leg_length_min <= value <= mech.leg_length_max]
    for line in outside:
        print('fk: warning: %s (the pose is geometric only: the legs cannot reach it)' % line,
              file=sys.stderr)
    if args.all:
        out = {'lengths': list(args.solve), 'count': len(modes),
               'modes': [_pose(m) for m in modes]}
    else:
        out = _pose(modes[0])
    if outside:
        out['outside_stroke'] = outside
    try:
        print(json.dumps(out, indent=2), flush=True)
    except BrokenPipeError:      # `fk --solve ... | head`: the reader left; no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


if __name__ == '__main__':
    sys.exit(main())
