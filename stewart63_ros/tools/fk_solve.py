"""``fk --solve L1 .. L6``: the platform pose from six leg lengths, as JSON, without DDS.

Prints the assembly mode nearest the parameter file's initial pose, or with
``--all`` every real assembly mode (nearest first). Each pose carries
position [m], theta [rad] (R = Rz Ry Rx, docs/interface.md), quaternion
(x, y, z, w), the Jacobian's condition number and whether it is flagged as
near-singular. Exit status 2 with a one-line reason on stderr when the
lengths admit no assembly; 1 when the parameter file is unusable.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

from stewart63_ros.core.fk import ForwardKinematics, NoAssemblyError
from stewart63_ros.core.params import ParameterError, load_mechanism


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='fk', description='Forward kinematics of the 6-3 platform from six leg lengths '
        '(no ROS needed). Prints JSON on stdout.')
    parser.add_argument('--solve', nargs=6, type=_length, required=True, metavar='L',
                        help='the six leg lengths L1 .. L6 [m]')
    parser.add_argument('--params', metavar='FILE', default=None,
                        help='ROS 2 parameter file (default: the packaged config/stewart63.yaml)')
    parser.add_argument('--all', action='store_true',
                        help='print every assembly mode, nearest the initial pose first')
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        mech = load_mechanism(args.params)
    except (ParameterError, FileNotFoundError) as exc:
        print('fk: %s' % exc, file=sys.stderr)
        return 1
    try:
        modes = ForwardKinematics(mech).all_modes(args.solve)
    except NoAssemblyError as exc:
        print('fk: no assembly: %s' % exc, file=sys.stderr)
        return 2
    if args.all:
        out = {'lengths': list(args.solve), 'count': len(modes),
               'modes': [_pose(m) for m in modes]}
    else:
        out = _pose(modes[0])
    try:
        print(json.dumps(out, indent=2), flush=True)
    except BrokenPipeError:      # `fk --solve ... | head`: the reader left; no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


if __name__ == '__main__':
    sys.exit(main())
