"""``record``: record the rig's topics into a new rosbag2 directory (MCAP storage).

    record DIR [--topics T ...] [--namespace NS] [--duration S]
               [--ready-file F] [--wait-for-publishers T ...] [--wait-timeout S]
    record --recover DIR

The CDR bytes are written exactly as received (raw subscriptions, no decoding),
stamped with their reception time, with the publishers' offered QoS in the
bag's metadata. See docs/bags.md for the readiness handshake and recovery.
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

from stewart63_ros.runtime import recorders

# Light imports only up to main's first line, which installs the stop
# handlers (the recorder's modules, rclpy and rosbags, load after them): a
# Ctrl-C while they load could otherwise be swallowed by a library's catch-all.
from stewart63_ros.runtime.launcher import (
    StopSignals,
    dump_stacks_on_sigusr1,
    end_process,
    ignore_stop_signals,
)
from stewart63_ros.runtime.ros_args import rclpy_args, split_ros_args
from stewart63_ros.tools.cli import quiet_on_closed_pipe


# ---------------------------------------------------------------- command line
def _parser():
    p = argparse.ArgumentParser(
        prog='record',
        description='Record the rig\'s topics into a new rosbag2 directory (MCAP storage). '
                    'Stops cleanly on Ctrl-C or SIGTERM.',
        epilog='Lines on stdout: "READY" once every subscription exists, "MATCHED" once '
               'every --wait-for-publishers topic has a matched publisher, and a summary '
               'at the end. ROS arguments go after --ros-args.')
    p.add_argument('bag', nargs='?', metavar='DIR',
                   help='new bag directory (must not exist); with --recover, the bag to repair')
    p.add_argument('-o', '--output', metavar='DIR', help='same as DIR')
    p.add_argument('--topics', nargs='+', metavar='T',
                   help='topics to record (default: every topic of the rig); relative '
                        'names resolve under the namespace')
    p.add_argument('--namespace', metavar='NS', help='namespace of the rig to record')
    p.add_argument('--duration', type=float, metavar='S', help='stop after S seconds')
    p.add_argument('--ready-file', metavar='F',
                   help='create file F when ready (after MATCHED if --wait-for-publishers)')
    p.add_argument('--wait-for-publishers', nargs='*', metavar='T',
                   help='print MATCHED (and create --ready-file) once each topic T (default: '
                        'every recorded topic) has a matched publisher')
    p.add_argument('--wait-timeout', type=float, default=30.0, metavar='S',
                   help='give up waiting for publishers after S s (default 30; recording '
                        'goes on)')
    p.add_argument('--flush-period', type=float, default=0.5, metavar='S',
                   help='write buffered messages to disk every S s (default 0.5): what a '
                        'hard kill can lose')
    p.add_argument('--batch-period', type=float, default=0.005, metavar='S',
                   help='after taking messages, let the next ones gather for S s before '
                        'taking again (default 0.005; the middleware receives and '
                        'acknowledges them meanwhile, and their bag times are their '
                        'reception times): one wake-up per batch instead of one per '
                        'message leaves the CPU to the nodes being recorded; 0: take each '
                        'message at once')
    p.add_argument('--executor', action='store_true',
                   help='take messages through an rclpy executor instead of the faster '
                        'wait-set loop (for comparison)')
    p.add_argument('--recover', '--reindex', action='store_true',
                   help='repair DIR after a hard kill: rebuild the MCAP summary and '
                        'metadata.yaml from what is on disk')
    return p


def _write_ready_file(path, text):
    path = Path(path)
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(text + '\n')
    os.replace(tmp, path)


@quiet_on_closed_pipe
def main(argv=None) -> int:
    code = _record(argv)
    if argv is None:
        # Its own process (the command line): the bag is closed and the
        # summary printed; end past the interpreter's finalization, a fifth
        # of a second of a rig's stop (launcher.end_process).
        end_process(code)
    return code


def _record(argv=None) -> int:
    made = []                   # the Recorder, once made
    stop = threading.Event()
    notes = []                  # this recorder's note for starting nodes (runtime/recorders.py)

    def stop_recording():
        stop.set()
        for note in notes:      # a stopping recorder: nobody is to wait for it
            recorders.withdraw(note)
        for rec in made:
            try:
                rec.request_stop()
            except RuntimeError:     # already closed: nothing left to stop
                pass
    # Kept until the process ends: a second signal (Ctrl-C twice, SIGINT then
    # SIGTERM from a launcher) while the bag is closed and rclpy shuts down
    # must not kill the process half way. One before the recorder exists:
    # it records nothing and ends at once, cleanly.
    StopSignals(stop_recording, deadline=True, interrupt=False).install()
    dump_stacks_on_sigusr1()
    # lazy: bagio, the recorder cost 973 ms; --help answers without
    from stewart63_ros.bagio import BagError
    from stewart63_ros.recording.recorder import Recorder
    from stewart63_ros.runtime.handshake import MATCHED_LINE, READY_LINE
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, ros = split_ros_args(argv)
    ros_args = rclpy_args('record', ros)
    args = _parser().parse_args(argv)
    bag = args.output or args.bag
    if not bag:
        _parser().error('give the bag directory (DIR or -o DIR)')

    if args.recover:
        # lazy: bagio costs 197 ms; --help answers without it
        from stewart63_ros.bagrepair import recover_bag
        try:
            counts = recover_bag(bag)
        except BagError as exc:
            print(f'record: error: {exc}', file=sys.stderr)
            return 2
        total = sum(counts.values())
        print(f'record: recovered {bag}: {total} messages ('
              + ', '.join(f'{t} {n}' for t, n in counts.items()) + ')', flush=True)
        return 0

    rec = Recorder(bag, args.topics, namespace=args.namespace, ros_args=ros_args,
                   flush_period=args.flush_period, fast_path=not args.executor,
                   batch_period=max(0.0, args.batch_period))
    made.append(rec)
    try:
        try:
            rec.open()
        except BagError as exc:
            print(f'record: error: {exc}', file=sys.stderr)
            return 2
        # Nodes started from here on wait for this recorder to match them
        # before their first message, though discovery has not shown it yet.
        notes.append(recorders.announce(rec.full_name, rec.domain_id))
        print(READY_LINE, flush=True)
        print(f'record: recording {len(rec.topics)} topics into {bag}', file=sys.stderr,
              flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        if args.wait_for_publishers is not None:
            wanted = args.wait_for_publishers or None
            deadline = time.monotonic() + args.wait_timeout
            ok = False
            while not stop.is_set():
                if rec.matched(wanted):
                    ok = True
                    break
                if time.monotonic() >= deadline:
                    break
                rec.spin_once(0.02)
            if ok:
                print(MATCHED_LINE, flush=True)
            elif not stop.is_set():
                missing = [t for t, n in rec.publisher_counts(wanted).items() if n < 1]
                print(f'record: warning: no publisher matched after {args.wait_timeout:g} s '
                      f'on {", ".join(missing)}; recording anyway', file=sys.stderr, flush=True)
        if args.ready_file:
            _write_ready_file(args.ready_file, 'ready')
        rec.run(duration=None if end is None else max(0.0, end - time.monotonic()),
                stop_event=stop)
        rec.close()
        print(rec.summary(), flush=True)
        return 0
    except BagError as exc:
        print(f'record: error: {exc}', file=sys.stderr)
        return 1
    finally:
        for note in notes:
            recorders.withdraw(note)
        try:
            rec.close()
        except Exception as exc:  # noqa: BLE001 - reported, the process ends anyway
            print(f'record: error while closing: {exc}', file=sys.stderr)
        ignore_stop_signals()


if __name__ == '__main__':
    sys.exit(main())
