"""view: the platform in 3D in a web browser, live from a rig or from a bag.

    view [--port P] [--host H] [--namespace NS] [--params FILE] [BAG [--run N]]

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

from stewart63_ros import bagio, bagruns
from stewart63_ros.bagio import BagError
from stewart63_ros.core.mechanics import markers as shapes_mod
from stewart63_ros.core.mechanics.fk import ForwardKinematics, NoAssemblyError
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.mechanics.rotation import (
    quaternion_from_rotation,
    rotation_from_euler,
    rotation_from_quaternion,
)
from stewart63_ros.core.plumbing.params import LEG_NAMES
from stewart63_ros.middleware import use_rig_profile
from stewart63_ros.runtime.launcher import StopSignals, dump_stacks_on_sigusr1
from stewart63_ros.tools.cli import load_checked, quiet_on_closed_pipe

#: Browser update rate [Hz]: viser pushes every change over a websocket; at
#: 1 kHz the page stops following, at 30 Hz it follows (measured).
FRAME_RATE = 30.0
PANEL_PERIOD = 0.25          # s between updates of the numbers on the page
NO_RIG_AFTER = 3.0           # s without a pose before the page says "no rig"
REFUSED = (0.85, 0.1, 0.1)


def rgb(color) -> tuple:
    return tuple(int(round(255 * c)) for c in color[:3])


# ------------------------------------------------------------------ the 3D scene
class ViewScene:
    """The rig's shapes as viser scene nodes, made once and moved per frame."""

    def __init__(self, server, setup):
        self.server = server
        self.mech = mech = setup.mechanism
        self.scene = shapes_mod.Scene(mech)
        sc = server.scene
        sc.set_up_direction('+z')
        server.initial_camera.position = (2.6, -2.4, 3.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.7)
        sc.add_grid('/grid', width=6.0, height=6.0, cell_size=0.5, position=(0, 0, -0.025))
        shapes = self.scene.shapes(setup.task.initial_position, np.eye(3))
        by = {(s.ns, s.id): s for s in shapes}
        base = by[('base', 0)]
        sc.add_cylinder('/base', radius=base.scale[0] / 2, height=base.scale[2],
                        color=rgb(base.color), position=tuple(base.position))
        for i, p in enumerate(mech.base_points):
            sc.add_icosphere('/ujoint_%d' % (i + 1), radius=self.scene.joint_d / 2,
                             color=rgb(by[('ujoints', 0)].color), position=tuple(p))
        # a 6-3's triangle and three vertices, a 6-6's hexagon and six joints
        plat = np.asarray(mech.platform_points, dtype=float)
        faces = self.scene.plate_faces
        # Hidden until the first state: a page with no rig shows the base only.
        self.platform = sc.add_frame('/platform', show_axes=True, axes_length=0.25,
                                     axes_radius=0.01, visible=False)
        sc.add_mesh_simple('/platform/plate', plat, faces, side='double',
                           color=rgb(by[('platform', 0)].color))
        for k, p in enumerate(plat):
            sc.add_icosphere('/platform/joint_%d' % (k + 1), radius=self.scene.joint_d / 2,
                             color=rgb(by[('platform_joints', 0)].color), position=tuple(p))
        self.ghost = sc.add_frame('/ghost', show_axes=False, visible=False)
        self.ghost_mesh = sc.add_mesh_simple('/ghost/plate', plat, faces, side='double',
                                             color=rgb(shapes_mod.ENDSTOP), opacity=0.35)
        self.cylinders, self.pistons, self.status = [], [], []
        for i in range(6):
            c, p, s = by[('cylinder', i)], by[('piston', i)], by[('leg_status', i)]
            self.cylinders.append(sc.add_cylinder(
                '/cylinder_%d' % (i + 1), radius=c.scale[0] / 2, height=c.scale[2],
                color=rgb(c.color), position=tuple(c.position), wxyz=_wxyz(c.orientation),
                visible=False))
            self.pistons.append(sc.add_cylinder(
                '/piston_%d' % (i + 1), radius=p.scale[0] / 2, height=p.scale[2],
                color=rgb(p.color), position=tuple(p.position), wxyz=_wxyz(p.orientation),
                visible=False))
            self.status.append(sc.add_icosphere(
                '/leg_status_%d' % (i + 1), radius=s.scale[0] / 2, color=rgb(shapes_mod.ENDSTOP),
                position=tuple(s.position), visible=False))
        self._ghost_pose = None
        self.shown = False

    def update(self, position, rot, lengths=None, forces=None):
        """Move everything to one state (call at most FRAME_RATE times a second)."""
        shapes = self.scene.shapes(position, rot, lengths, forces)
        by = {(s.ns, s.id): s for s in shapes}
        with self.server.atomic():
            self.platform.position = tuple(np.asarray(position, dtype=float))
            self.platform.wxyz = _wxyz(quaternion_from_rotation(rot))
            for i in range(6):
                for handle, shape in ((self.cylinders[i], by[('cylinder', i)]),
                                      (self.pistons[i], by[('piston', i)])):
                    handle.position = tuple(shape.position)
                    handle.wxyz = _wxyz(shape.orientation)
                    handle.height = float(shape.scale[2])
                    color = rgb(shape.color)
                    if tuple(handle.color) != color:
                        handle.color = color
                status = by[('leg_status', i)]
                shown = status.color[3] > 0
                self.status[i].position = tuple(status.position)
                if shown:
                    self.status[i].color = rgb(status.color)
                if self.status[i].visible != shown:
                    self.status[i].visible = shown
            if not self.shown:
                self.shown = True
                for handle in [self.platform] + self.cylinders + self.pistons:
                    handle.visible = True

    def set_ghost(self, pose, refused=False):
        """The setpoint pose (position, rot), or None to hide it."""
        key = None if pose is None else (tuple(np.round(pose[0], 9)),
                                         tuple(np.round(np.ravel(pose[1]), 9)), refused)
        if key == self._ghost_pose:
            return
        self._ghost_pose = key
        if pose is None:
            self.ghost.visible = False
            return
        self.ghost.position = tuple(np.asarray(pose[0], dtype=float))
        self.ghost.wxyz = _wxyz(quaternion_from_rotation(pose[1]))
        self.ghost_mesh.color = rgb(REFUSED if refused else shapes_mod.ENDSTOP)
        self.ghost.visible = True


def _wxyz(quat_xyzw) -> tuple:
    x, y, z, w = (float(v) for v in quat_xyzw)
    return (w, x, y, z)


def _quat_xyzw(wxyz) -> np.ndarray:
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([x, y, z, w])


# ------------------------------------------------------------------ live rig
class LiveSource:
    """The newest state of a rig over DDS, taken without an executor."""

    def __init__(self, namespace: str, setup):
        import rclpy  # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        from diagnostic_msgs.msg import DiagnosticArray

        # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState

        from stewart63_ros import topics
        self.mech = mech = setup.mechanism
        self.fk = ForwardKinematics(mech, start=(setup.task.initial_position,
                                                 setup.task.initial_rotation))
        use_rig_profile()
        rclpy.init(args=['view'])
        ns = namespace.strip('/')
        self.namespace = '/' + ns if ns else '/'
        self.node = rclpy.create_node('view', namespace=self.namespace,
                                      start_parameter_services=False)
        newest = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        noop = lambda _msg: None  # noqa: E731 - taken directly, never called back
        mk = self.node.create_subscription
        self.subs = {
            'pose': mk(PoseStamped, topics.PLATFORM_POSE, noop, newest),
            'lengths': mk(JointState, topics.LEG_LENGTHS, noop, newest, raw=True),
            'forces': mk(JointState, topics.LEG_FORCES, noop, newest, raw=True),
            'diagnostics': mk(DiagnosticArray, topics.DIAGNOSTICS, noop, topics.DIAGNOSTICS_QOS),
        }
        self.pose_topic = self.subs['pose'].topic_name
        self.setpoint_pub = self.node.create_publisher(PoseStamped, topics.POSE_SETPOINT,
                                                       topics.SETPOINT_QOS)
        self.pose = None            # (position, rot, stamp)
        self.lengths = None
        self.forces = None
        self.last_pose_wall = None
        self.statuses = {}          # name -> (level, message, {key: value})
        self.setpoint_lengths = np.asarray(setup.task.setpoint_lengths, dtype=float)
        self.ghost = self._fk(self.setpoint_lengths, None)
        self.started = time.monotonic()

    def _fk(self, lengths, near):
        try:
            ref = near if near is not None else self.fk.reference
            r = self.fk.nearest(lengths, *ref)
        except NoAssemblyError:
            return None
        return (np.asarray(r.position), np.asarray(r.rotation))

    def _newest(self, name):
        # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        from stewart63_ros.runtime.rclpy_internals import take
        sub, last = self.subs[name], None
        while True:
            msg = take(sub)
            if msg is None:
                return last
            last = msg

    def poll(self):
        """Take what came in since the last call."""
        # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        from stewart63_ros.runtime import rclpy_internals, wire
        msg = self._newest('pose')
        if msg is not None:
            p, q = msg.pose.position, msg.pose.orientation
            quat = np.array([q.x, q.y, q.z, q.w])
            if np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 0.5:
                self.pose = (np.array([p.x, p.y, p.z]), rotation_from_quaternion(quat))
                self.last_pose_wall = time.monotonic()
        for name, field in (('lengths', 'position'), ('forces', 'effort')):
            data = self._newest(name)
            if data is not None:
                fast = wire.read_joint_state(data, (field,))
                if fast is not None:
                    setattr(self, name, fast[3][field])
        while True:
            msg = rclpy_internals.take(self.subs['diagnostics'])
            if msg is None:
                break
            for status in msg.status:
                if self._mine(status.name):
                    self.statuses[status.name] = (
                        int.from_bytes(status.level, 'little') if isinstance(
                            status.level, bytes) else int(status.level),
                        status.message, {kv.key: kv.value for kv in status.values})
        self._setpoint_from_controller()

    def _mine(self, status_name: str) -> bool:
        """A status of a node of this rig ('stewart63' + node's full name)."""
        if not status_name.startswith('stewart63/'):
            return False
        node_ns = status_name[len('stewart63'):].rsplit('/', 1)[0] or '/'
        return node_ns == self.namespace

    def _setpoint_from_controller(self):
        for name, (_, _, values) in self.statuses.items():
            if name.endswith('/controller') and 'setpoint' in values:
                try:
                    lengths = np.array([float(v) for v in
                                        values['setpoint'].strip('[]').split(',')])
                except ValueError:
                    return
                if lengths.shape == (6,) and not np.allclose(lengths, self.setpoint_lengths):
                    self.setpoint_lengths = lengths
                    ghost = self._fk(lengths, self.ghost)
                    if ghost is not None:
                        self.ghost = ghost

    def rig_present(self) -> bool:
        return self.node.count_publishers(self.pose_topic) > 0

    def controller_rejections(self) -> tuple:
        """(count of refused pose setpoints, the controller's message)."""
        for name, (_, message, values) in self.statuses.items():
            if name.endswith('/controller'):
                n = sum(int(v) for k, v in values.items()
                        if k.startswith('rejected/pose_setpoint/'))
                return n, message
        return 0, ''

    def publish_setpoint(self, position, quat_xyzw):
        # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        from geometry_msgs.msg import PoseStamped
        msg = PoseStamped()
        msg.header.frame_id = 'base'
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (
            float(v) for v in position)
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = (float(v) for v in quat_xyzw)
        self.setpoint_pub.publish(msg)

    def close(self):
        import rclpy  # lazy: rclpy costs 302 ms; view of a bag needs no ROS
        self.node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}


def live_panel(src: LiveSource) -> str:
    """The numbers on the page, as markdown."""
    lines = []
    if src.pose is None or time.monotonic() - (src.last_pose_wall or 0) > NO_RIG_AFTER:
        waited = time.monotonic() - src.started
        if not src.rig_present():
            lines.append('**No rig in namespace `%s`**: nothing publishes `%s` yet. '
                         'Waiting (%.0f s)…' % (src.namespace, src.pose_topic, waited))
        else:
            lines.append('**Rig found in `%s`, no pose for %.0f s** (stopped or paused?). '
                         'Waiting…' % (src.namespace, time.monotonic() - (
                             src.last_pose_wall or src.started)))
    else:
        p = src.pose[0]
        lines.append('**Live** `%s`: platform at x %.3f, y %.3f, z %.3f m'
                     % (src.namespace, p[0], p[1], p[2]))
    if src.lengths is not None:
        err = src.lengths - src.setpoint_lengths
        worst = int(np.argmax(np.abs(err)))
        lines.append('Tracking error: max |L − L0| = %.1f mm (%s), %.3f %% of L0'
                     % (1e3 * abs(err[worst]), LEG_NAMES[worst],
                        100 * np.max(np.abs(err) / src.setpoint_lengths)))
    if src.forces is not None:
        lines.append('Forces [N]: ' + ', '.join('%.0f' % f for f in src.forces))
    for name, (level, message, values) in sorted(src.statuses.items()):
        short = name.rsplit('/', 1)[-1]
        extra = ''
        if 'latency/p99_ms' in values:
            extra = ' — loop latency p50 %s ms, p99 %s ms' % (
                values.get('latency/p50_ms', '?'), values['latency/p99_ms'])
        lines.append('`%s` **%s** %s%s' % (short, LEVELS.get(level, level), message, extra))
        lines += run_lines(values)
    return '\n\n'.join(lines)


def run_lines(values: dict) -> list:
    """What a plant's status says about its run beyond the message: paused
    or resetting (``run``), and each injected fault (``fault: <fault>``) with
    its state, active ones first."""
    lines = []
    run = values.get('run')
    if run in ('paused', 'reset', 'stepping'):
        lines.append('&nbsp;&nbsp;run **%s** at sample %s (run %s)' % (
            'resetting' if run == 'reset' else run, values.get('sample', '?'),
            values.get('run_number', '?')))
    faults = sorted(((k[len('fault: '):], v) for k, v in values.items()
                     if k.startswith('fault: ')), key=lambda kv: not kv[1].startswith('active'))
    for name, state in faults:
        mark = '**' if state.startswith('active') else ''
        lines.append('&nbsp;&nbsp;fault `%s`: %s%s%s' % (name, mark, state, mark))
    return lines


# ------------------------------------------------------------------ bag
class BagRun:
    """A recorded run: poses, lengths, forces and the ghost against time. A bag
    that spans a reset holds several runs (``bagruns.bag_runs``): one of them,
    ``number`` (``--run``; default the last), never several joined."""

    def __init__(self, bag, setup, number=None):
        runs = bagruns.bag_runs(bag)
        self.run = bagruns.select_run(runs, number) if runs else None
        self.others = [r for r in runs if r is not self.run]
        cols = bagruns.trajectory_from_bag(bag, hold_forces=True, run=self.run)
        t = cols['t']
        have = np.all(np.isfinite(np.column_stack([cols[c] for c in (
            'x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')])), axis=1) if len(t) else \
            np.zeros(0, bool)
        if not have.any():
            reader = bagio.open_reader(bag)
            try:
                topics = sorted({c.topic for c in reader.connections})
            finally:
                reader.close()
            raise bagio.BagError(
                '%s: no platform poses (neither ground_truth/pose nor platform_pose) in the '
                'bag (it has: %s)' % (bag, ', '.join(topics) or 'no topics'))
        self.t = t[have]
        self.position = np.column_stack([cols[c][have] for c in ('x', 'y', 'z')])
        theta = np.column_stack([cols[c][have] for c in ('theta_x', 'theta_y', 'theta_z')])
        self.rot = np.array([rotation_from_euler(th) for th in theta])
        lengths = np.column_stack([cols['L%d' % i][have] for i in range(1, 7)])
        self.lengths = lengths if np.all(np.isfinite(lengths)) else None
        forces = np.column_stack([cols['F%d' % i][have] for i in range(1, 7)])
        self.forces = forces
        self.ghost_t, self.ghost = self._ghosts(bag, setup, cols)

    def _ghosts(self, bag, setup, cols):
        """Ghost poses against time from the bag's markers (their 'ghost'
        plate), else one from its setpoints, else the parameter file's."""
        mech = setup.mechanism
        # the plate's first winding: its joints, face by face (markers.Scene)
        joints = shapes_mod.plate_faces(mech.platform_points).ravel()
        t0 = None
        times, poses = [], []
        try:
            for _, _, msg in bagio.read_messages(bag, ['markers'], run=self.run):
                for m in msg.markers:
                    if m.ns == 'ghost' and m.color.a > 0 and len(m.points) >= joints.size:
                        verts = np.array([[p.x, p.y, p.z] for p in m.points[:joints.size]])
                        stamp = m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec
                        times.append(stamp)
                        poses.append(_pose_from_vertices(verts, mech, joints))
        except bagio.BagError:
            pass
        if times:
            # same clock as the samples: the trajectory's t is stamp - first stamp
            first = self._first_stamp(bag, self.run)
            t0 = first if first is not None else times[0]
            return np.array(times) - t0, poses
        fk = ForwardKinematics(mech)
        try:
            r = fk.nearest(np.asarray(setup.task.setpoint_lengths), self.position[0],
                           self.rot[0])
            return np.array([0.0]), [(np.asarray(r.position), np.asarray(r.rotation))]
        except NoAssemblyError:
            return np.array([0.0]), [None]

    @staticmethod
    def _first_stamp(bag, run=None):
        for topic in ('leg_lengths', 'ground_truth/pose', 'platform_pose'):
            try:
                for _, _, msg in bagio.read_messages(bag, [topic], run=run):
                    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            except bagio.BagError:
                continue
        return None

    def index(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t, side='right') - 1, 0, len(self.t) - 1))

    def describe(self) -> str:
        """Which run of the bag this is, and how to see the others ('' for a bag of one)."""
        if self.run is None or not self.others:
            return ''
        return '%s of the bag (%d of %d; the others: %s)' % (
            self.run.name, self.run.index, self.run.count,
            ', '.join('--run %d' % (r.number if r.number is not None else r.index)
                      for r in self.others))

    def ghost_at(self, t: float):
        k = int(np.searchsorted(self.ghost_t, t, side='right') - 1)
        return self.ghost[max(k, 0)]


def _pose_from_vertices(verts, mech, joints=None):
    """(t, R) with R p_k + t = v_k (least squares: Kabsch); ``joints``: the row of
    ``platform_points`` of each v_k (default: all, in order)."""
    plat = np.asarray(mech.platform_points, dtype=float)
    if joints is not None:
        plat = plat[joints]
    pc, vc = plat.mean(axis=0), verts.mean(axis=0)
    u, _, vt = np.linalg.svd((plat - pc).T @ (verts - vc))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return (vc - rot @ pc, rot)


# ------------------------------------------------------------------ serving
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
