"""The supervisor's homing (nodes/supervisor.py): the forces that find each
leg's zero, and setting the offsets found on the node that owns the sensors'
zero (the plant, or on the bus the bridge). A part of ``SupervisorNode``,
apart by job; core/machine/supervisor_motion.py computes the homing itself."""
from __future__ import annotations

import numpy as np
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter

from stewart63_ros import topics


class SupervisorHoming:
    """Homing for ``SupervisorNode`` (uses its ``core``, ``health``, logger
    and executor)."""

    def connect_zero_node(self) -> None:
        """The parameter client of ``zero_node`` (``homed_offset_node``)."""
        self.zero_peer = None   # that node, when composed with this one (nodes/composed.py)
        self.zero_parameters = self.create_client(SetParameters, '%s/set_parameters' % (
            topics.node_full_name(self.get_namespace(), self.zero_node)))

    def home(self, ns: int):
        """The homing's forces for sample ``ns``; once every leg is found, the
        offsets are set (the ``homed_offset`` of the plant, or of the bridge:
        the drives' home offsets) before this sample is answered, so its next
        sample reads true."""
        forces = self.core.homing_forces(ns)
        zero = self.core.take_zero_to_set()
        if zero is not None:
            self.health.values['homing/offsets'] = np.round(zero, 6).tolist()
            why = self.set_zero(zero)
            if why:
                self.core.trip_now('homing', why, ns)
                return self.core.safe_forces(ns)
            self.get_logger().info('homed: offsets %s m set on the %s'
                                   % (np.round(zero, 6).tolist(), self.zero_node))
        if self.core.homed:
            self.health.values['homed'] = 'true'
            self.report()
        return forces

    def set_zero_again(self) -> str:
        """A reset of a ``homing`` trip: the offsets found, set again; '' or
        why they were refused again (the reset is then refused)."""
        why = self.set_zero(self.core.offsets)
        if not why:
            self.get_logger().info('homed: offsets %s m set on the %s at the reset'
                                   % (np.round(self.core.offsets, 6).tolist(), self.zero_node))
        return why

    def set_zero(self, zero) -> str:
        """``homed_offset`` of the plant (or bridge) of this namespace; '' or
        why it failed."""
        value = [float(v) for v in zero]
        if self.zero_peer is not None:
            # Composed with it (nodes/composed.py): its parameter service is
            # served by its own executor, which nobody spins while this waits.
            result = self.zero_peer.set_parameters([Parameter('homed_offset', value=value)])[0]
            return '' if result.successful else 'the %s refused: %s' % (self.zero_node,
                                                                        result.reason)
        client = self.zero_parameters
        if not client.wait_for_service(timeout_sec=5.0):
            return '%s: no such service' % client.srv_name
        future = client.call_async(SetParameters.Request(parameters=[Parameter(
            'homed_offset', value=value).to_parameter_msg()]))
        self.executor_.spin_until_future_complete(future, timeout_sec=10.0)
        if not future.done():
            return '%s: no answer within 10 s' % client.srv_name
        result = future.result().results[0]
        return '' if result.successful else 'the %s refused: %s' % (self.zero_node,
                                                                    result.reason)
