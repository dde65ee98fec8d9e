"""view: the platform in 3D in a web browser, live from a rig or from a bag.

    view [--port P] [--host H] [--namespace NS] [--params FILE] [BAG [--run N]]

The scene is ``view_scene``'s, what it shows (a live rig or a bag)
``view_sources``'; this module serves them and is the command.

Serves ``http://localhost:P/`` (default port 8080) with viser: a page the
package serves itself, no network needed. The scene is the one of the
``markers`` topic (core/mechanics/markers.py): base, U-joints, legs coloured by force,
platform, setpoint ghost.

Live (no BAG): follows ``platform_pose``, ``leg_lengths`` and ``leg_forces``
of the rig in NS, redrawn at 30 Hz from the newest message of each (taken
directly, no callback per message; best-effort depth-1 subscriptions, so the
rig's publishers never wait for the page); the panel shows the tracking
error, the loop latency and every node's /diagnostics state. Drag the ghost's
handle to move the setpoint: the pose is published on ``pose_setpoint``
(a pose outside the stroke is refused on the page and not sent; one the
controller refuses is shown as refused). With no rig in NS the page says so
and keeps waiting.

With BAG: the recorded run, with play/pause and a time slider (poses from
``ground_truth/pose`` or else ``platform_pose``; the ghost from the bag's
``markers`` or setpoints). A bag that spans a reset holds several runs: the
last is replayed, ``--run N`` replays run N; the page names the others.
"""
from __future__ import annotations

import argparse
import errno
import logging
import socket
import sys
import threading
import time

import numpy as np

from stewart63_ros.bagio import BagError
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import (
    quaternion_from_rotation,
    rotation_from_quaternion,
)
from stewart63_ros.core.plumbing.params import LEG_NAMES
from stewart63_ros.runtime.launcher import StopSignals, dump_stacks_on_sigusr1
from stewart63_ros.tools.cli import load_checked, quiet_on_closed_pipe
from stewart63_ros.tools.view_scene import (
    FRAME_RATE,
    PANEL_PERIOD,
    ViewScene,
    _quat_xyzw,
    _wxyz,
)
from stewart63_ros.tools.view_sources import (
    BagRun,
    LiveSource,
    live_panel,
)


def port_free(host: str, port: int) -> str:
    """'' if ``host:port`` can be bound now, else why not."""
    if port == 0:
        return ''
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return 'port %d is in use (another view or server?); choose one with --port' % port
            return 'cannot listen on %s:%d: %s' % (host, port, exc.strerror)
    return ''


def start_server(host: str, port: int):

    import viser  # lazy: viser costs 1623 ms; --help answers without it
    logging.getLogger('websockets').setLevel(logging.ERROR)
    server = viser.ViserServer(host=host, port=port, label='stewart63', verbose=False)
    if port and server.get_port() != port:       # viser moves on to the next free port
        server.stop()
        raise OSError('port %d is in use (another view or server?); choose one with --port'
                      % port)
    return server


def url_of(host: str, port: int) -> str:
    shown = 'localhost' if host in ('0.0.0.0', '127.0.0.1', 'localhost', '::') else host
    return 'http://%s:%d/' % (shown, port)


def run_live(server, setup, namespace, stop):
    mech = setup.mechanism
    view = ViewScene(server, setup)
    src = LiveSource(namespace, setup)
    gui = server.gui
    with gui.add_folder('Rig'):
        panel = gui.add_markdown('Starting…')
    with gui.add_folder('Setpoint'):
        gui.add_markdown('Drag the handle at the ghost (yellow) to move the setpoint; '
                         'it is published on `pose_setpoint`.')
        setpoint_note = gui.add_markdown('')
    handle = server.scene.add_transform_controls('/setpoint_handle', scale=0.4,
                                                 depth_test=False)
    dragged = {}
    lock = threading.Lock()

    @handle.on_update
    def _(_event):
        with lock:
            dragged['pose'] = (np.array(handle.position), _quat_xyzw(handle.wxyz))

    last_panel = 0.0
    last_sent = 0.0
    sent = None             # (time, controller rejections before)
    refused_local = False
    period = 1.0 / FRAME_RATE
    handle_at = None
    while not stop.is_set():
        tick = time.monotonic()
        src.poll()
        if src.pose is not None:
            view.update(src.pose[0], src.pose[1], src.lengths, src.forces)
        with lock:
            # At most one setpoint per 0.1 s; the newest drag waits its turn
            # (the last position of a drag is always sent).
            pending = 'pose' in dragged
            pose = dragged.pop('pose') if pending and tick - last_sent > 0.1 else None
        if pose is not None:
            rot = rotation_from_quaternion(pose[1])
            lengths = leg_lengths(mech, pose[0], rot)
            bad = np.flatnonzero((lengths < mech.leg_length_min) |
                                 (lengths > mech.leg_length_max))
            if bad.size:
                refused_local = True
                setpoint_note.content = (
                    '**Refused**: %s would need %.3f m, outside the stroke [%g, %g] m; '
                    'not sent.' % (LEG_NAMES[bad[0]], lengths[bad[0]],
                                   mech.leg_length_min, mech.leg_length_max))
                view.set_ghost((pose[0], rot), refused=True)
            else:
                refused_local = False
                src.publish_setpoint(pose[0], pose[1])
                sent = (tick, src.controller_rejections()[0])
                setpoint_note.content = 'Sent: x %.3f, y %.3f, z %.3f m' % tuple(pose[0])
                view.set_ghost((pose[0], rot))
            last_sent = tick
        elif not pending and not refused_local:
            view.set_ghost(src.ghost)
            if src.ghost is not None and handle_at is None:
                handle.position = tuple(src.ghost[0])
                handle.wxyz = _wxyz(quaternion_from_rotation(src.ghost[1]))
                handle_at = src.ghost
        if sent is not None:
            count, message = src.controller_rejections()
            if count > sent[1]:
                setpoint_note.content = '**Refused by the controller**: %s' % message
                view.set_ghost(src.ghost, refused=True)
                sent = None
            elif tick - sent[0] > 3.0:
                sent = None
        if tick - last_panel > PANEL_PERIOD:
            panel.content = live_panel(src)
            last_panel = tick
        stop.wait(max(0.0, period - (time.monotonic() - tick)))
    src.close()


def run_bag(server, setup, bag_run: BagRun, stop):
    view = ViewScene(server, setup)
    gui = server.gui
    end = float(bag_run.t[-1])
    step = max(1e-3, round(end / 1000.0, 3)) if end > 0 else 1e-3
    with gui.add_folder('Bag'):
        info = gui.add_markdown('')
        play = gui.add_checkbox('Play', initial_value=False)
        speed = gui.add_dropdown('Speed', ('0.25', '0.5', '1', '2', '4'), initial_value='1')
        slider = gui.add_slider('Time [s]', min=0.0, max=max(end, step), step=step,
                                initial_value=0.0)
    state = {'t': 0.0, 'set_by_us': None}

    @slider.on_update
    def _(_event):
        if state['set_by_us'] is None or abs(slider.value - state['set_by_us']) > 1e-9:
            state['t'] = float(slider.value)

    period = 1.0 / FRAME_RATE
    last = time.monotonic()
    shown = None
    while not stop.is_set():
        now = time.monotonic()
        if play.value:
            state['t'] += (now - last) * float(speed.value)
            if state['t'] >= end:
                state['t'] = end
                play.value = False
            state['set_by_us'] = round(state['t'] / step) * step
            slider.value = state['set_by_us']
        last = now
        k = bag_run.index(state['t'])
        if k != shown:
            shown = k
            view.update(bag_run.position[k], bag_run.rot[k],
                        None if bag_run.lengths is None else bag_run.lengths[k],
                        bag_run.forces[k])
            view.set_ghost(bag_run.ghost_at(bag_run.t[k]))
            f = bag_run.forces[k]
            info.content = ('%st = %.3f s of %.3f s\n\nplatform z %.4f m\n\nforces [N]: %s'
                            % ('%s\n\n' % bag_run.describe() if bag_run.describe() else '',
                               bag_run.t[k], end, bag_run.position[k][2],
                               ', '.join('%.0f' % v for v in f) if np.all(np.isfinite(f))
                               else 'not recorded'))
        stop.wait(max(0.0, period - (time.monotonic() - now)))


@quiet_on_closed_pipe
def main(argv=None) -> int:
    dump_stacks_on_sigusr1()
    parser = argparse.ArgumentParser(
        prog='view', description=__doc__.split('\n\n')[0],
        epilog='Open the printed URL in a browser. Live: Ctrl-C stops the page; the rig '
               'runs on. The page works offline (served by the package).')
    parser.add_argument('bag', nargs='?', metavar='BAG', help='a recorded bag directory to '
                        'replay (default: live from the rig)')
    parser.add_argument('--port', type=int, default=8080,
                        help='HTTP port (default 8080; 0: any free port)')
    parser.add_argument('--host', default='127.0.0.1',
                        help='address to listen on (default 127.0.0.1, this machine only; '
                        '0.0.0.0 for every interface)')
    parser.add_argument('--namespace', default='', help='namespace of the rig, e.g. /rig2')
    parser.add_argument('--params', help='parameter file of the mechanism (default: the '
                        'packaged one)')
    parser.add_argument('--run', type=int, default=None, metavar='N',
                        help='a bag that spans a reset: replay its run N (default: the last)')
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        print('view: error: --port must be from 0 to 65535', file=sys.stderr)
        return 2
    if args.bag and args.namespace:
        print('view: error: --namespace is for a live rig, not with a BAG', file=sys.stderr)
        return 2
    if args.run is not None and not args.bag:
        print('view: error: --run goes with a BAG', file=sys.stderr)
        return 2
    setup = load_checked('view', args.params)
    if setup is None:
        return 2
    bag_run = None
    if args.bag:
        try:
            bag_run = BagRun(args.bag, setup, args.run)
        except BagError as exc:
            print('view: error: %s' % exc, file=sys.stderr)
            return 2
    problem = port_free(args.host, args.port)
    if problem:
        print('view: error: %s' % problem, file=sys.stderr)
        return 2
    try:
        server = start_server(args.host, args.port)
    except OSError as exc:
        print('view: error: %s' % exc, file=sys.stderr)
        return 2
    print('view: %s (%s); Ctrl-C stops' % (
        url_of(args.host, server.get_port()),
        ('bag %s' % args.bag + (', %s' % bag_run.describe() if bag_run.describe() else ''))
        if args.bag else 'live, namespace %s' % (args.namespace or '/')),
        flush=True)
    stop = threading.Event()
    StopSignals(stop.set, deadline=False, interrupt=False).install()
    try:
        if bag_run is not None:
            run_bag(server, setup, bag_run, stop)
        else:
            run_live(server, setup, args.namespace, stop)
    finally:
        server.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
