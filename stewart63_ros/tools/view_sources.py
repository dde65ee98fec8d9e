"""What the view shows: a live rig (``LiveSource``: the poses, lengths and
/diagnostics it subscribes to, and the page's panel) or a recorded bag
(``BagRun``: one run of the plant, played back).
"""
from __future__ import annotations

import time

import numpy as np

from stewart63_ros import bagio, bagruns
from stewart63_ros.core.mechanics import markers as shapes_mod
from stewart63_ros.core.mechanics.fk import ForwardKinematics, NoAssemblyError
from stewart63_ros.core.mechanics.rotation import (
    rotation_from_euler,
    rotation_from_quaternion,
)
from stewart63_ros.core.plumbing.params import LEG_NAMES
from stewart63_ros.middleware import use_rig_profile
from stewart63_ros.tools.view_scene import (
    NO_RIG_AFTER,
)


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
