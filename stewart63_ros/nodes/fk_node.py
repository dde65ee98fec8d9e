"""fk: the platform pose and twist from measured leg lengths.

On every ``leg_lengths`` sample: tracking forward kinematics (Newton from the
previous pose, all-modes fallback) -> ``platform_pose`` and ``platform_twist``
stamped with the sample's stamp. Lengths with no assembly, or a pose whose
Jacobian condition number exceeds ``singularity_threshold``, are reported on
/diagnostics and nothing is published for that sample.

``markers`` (RViz2, Foxglove): at ``marker_rate`` Hz (default 30; 0: off)
a timer draws the newest sample, its pose and the newest ``leg_forces``
(nodes/markers.py); the sample path only stores references for it.

The ``fk`` executable is ``tools/fk.py``: this node, or with ``--solve`` one
solution printed as JSON without DDS (``tools/fk_solve.py``).
"""
from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PoseStamped, TwistStamped
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.core.mechanics.fk import FKTracker, NoAssemblyError
from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.nodes.markers import MarkerPublisher
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.base import RigNode
from stewart63_ros.runtime.checks import RESTART_PAUSE, Rejected, StampGate, source_of
from stewart63_ros.runtime.launcher import run
from stewart63_ros.runtime.lockstep import ProgressPublisher


class FKNode(RigNode):
    def __init__(self, options):
        super().__init__('fk')
        threshold = self.param('singularity_threshold')
        task = self.setup.task
        self.tracker = FKTracker(self.mech, task.initial_position, task.initial_rotation,
                                 cond_threshold=threshold)
        self.offset = self.param('leg_length_offset')
        self.warm_up()
        self.gate = StampGate(RESTART_PAUSE)
        self.singular = 0
        self.no_assembly = 0
        self.pub_pose = self.publisher(PoseStamped, topics.PLATFORM_POSE, topics.STREAM_PUB)
        self.pub_twist = self.publisher(TwistStamped, topics.PLATFORM_TWIST,
                                        topics.STREAM_PUB)
        self.pose_out = wire.FrameTemplates(wire.pose_template)
        self.twist_out = wire.FrameTemplates(wire.twist_template)
        for out in (self.pose_out, self.twist_out):     # made now, not on sample 1
            out.get('base')
        self.send_pose = self.health.sender(topics.PLATFORM_POSE, self.pub_pose)
        self.send_twist = self.health.sender(topics.PLATFORM_TWIST, self.pub_twist)
        wire.warm_up(('position',), ('velocity',))
        self.markers = None
        rate = self.param('marker_rate')
        if rate:
            self.markers = MarkerPublisher(self, self.setup, float(rate), self.tracker.fk)
        self.sub_samples = None         # made once its outputs are matched
        # Every sample must reach fk; in lockstep it tells the plant how far it
        # has got (runtime/lockstep.py), so the plant never outruns it.
        self.health.every_message.add(topics.LEG_LENGTHS)
        self.lockstep = self.param('clock_mode') == 'lockstep'
        self.progress = None
        if self.lockstep:
            self.progress = ProgressPublisher(self)
            self.after_batch = self.progress.publish

    def subscribe_input(self):
        """``leg_lengths``, once fk's outputs are matched (RigNode.subscribe_input)."""
        if self.sub_samples is not None:
            return
        # Every sample gets a pose: a short queue rather than newest-only.
        # Serialized samples in, serialized poses out: see runtime/wire.py.
        self.sub_samples = self.create_subscription(JointState, topics.LEG_LENGTHS,
                                                    self.on_sample, topics.EVERY_SUB,
                                                    raw=True)
        self.watch_source(self.sub_samples, topics.LEG_LENGTHS, self.gate)

    def warm_up(self):
        """Compile / load the solver kernels now, not on the first sample."""
        task = self.setup.task
        lengths = leg_lengths(self.mech, task.initial_position, task.initial_rotation)
        self.tracker.solve(lengths, np.zeros(6))
        self.tracker.fk.all_modes(lengths)
        self.tracker.reset(task.initial_position, task.initial_rotation)

    def on_sample(self, data, info):
        self.health.received[topics.LEG_LENGTHS] += 1
        source = source_of(info)
        self.count_skips(topics.LEG_LENGTHS, source, info)
        try:
            ns, sec, nanosec, frame_id, values = wire.joint_state_sample(
                data, self.gate, ('position',), ('velocity',), source=source)
        except Rejected as exc:
            self.health.reject(topics.LEG_LENGTHS, exc)
            if self.progress is not None and exc.stamp_ns is not None:
                # A dropout's NaN sample is handled too (refused): the
                # plant, which waits for fk's progress, must not wait for it.
                self.progress.note(exc.stamp_ns)
            return
        if self.progress is not None:
            self.progress.note(ns)      # handled, whether a pose comes of it or not
        if self.gate.new_run:
            # Another run (a bag played again): track from the pose it starts at.
            self.tracker.reset(self.setup.task.initial_position,
                               self.setup.task.initial_rotation)
        self.accept_sample(self.gate, ns, source, topics.LEG_LENGTHS)
        rates = values.get('velocity')
        # The sensors read the true length plus leg_length_offset (the file's).
        lengths = values['position'] - self.offset
        try:
            result = self.tracker.solve(lengths, rates)
        except NoAssemblyError as exc:
            self.no_assembly += 1
            self.health.reject(topics.LEG_LENGTHS, Rejected('no_assembly', str(exc)))
            return
        if result.singular:
            self.singular += 1
            self.health.warning = ('near-singular pose (Jacobian condition %.3g): not '
                                   'published' % result.condition)
            return
        self.send_pose(self.pose_out.get(frame_id).fill(
            sec, nanosec, position=result.position, orientation=result.quaternion))
        if self.markers is not None:       # references only: drawn by its timer
            self.markers.sample = (sec, nanosec, lengths, result.position,
                                   result.rotation)
        if rates is not None:
            self.send_twist(self.twist_out.get(frame_id).fill(
                sec, nanosec, linear=result.velocity, angular=result.omega))

    #: s: in lockstep (``clock_mode``), how long fk lets samples gather
    #: between two batches (see RigNode.run_on): nothing waits for its poses
    #: there, and a wake-up per sample costs the CPU the plant and the
    #: controller need for the next one. Every sample still gets its pose.
    LOCKSTEP_BATCH_PERIOD = 0.005

    def run(self):
        self.wait_for_matches()         # (its input: made as the wait ends)
        self.run_on(self.sub_samples, self.LOCKSTEP_BATCH_PERIOD if self.lockstep else 0.0)

    def report(self):
        self.health.values.update(singular_samples=self.singular,
                                  no_assembly_samples=self.no_assembly)
        if self.markers is not None:
            self.health.published[topics.MARKERS] = self.markers.published
        super().report()
        if self.started:
            self.health.warning = ''


def main(argv=None, extra_args=None):
    """Run the node; ``extra_args(parser)`` adds options to its ``--help``."""
    argv = list(sys.argv if argv is None else argv)
    sys.exit(run('fk', __doc__.split('\n\n')[0], FKNode, argv, extra_args=extra_args))


if __name__ == '__main__':
    main()
