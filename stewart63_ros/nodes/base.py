"""RigNode: the rclpy Node every stewart63 node derives from."""
from __future__ import annotations

import time

from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from stewart63_ros.core.params import ParameterError, mechanism_from_params
from stewart63_ros.nodes.common import DirectTake, Health, node_parameters, wait_until


class RigNode(Node):
    """Loads the mechanism from the node's parameters and owns the diagnostics.

    Node-specific keys shared by all nodes (README, "Parameters"):
    ``wait_for_subscribers`` (int, 0): before its first message, wait until
    every data publisher of this node has that many matched subscriptions
    (``rig --record`` sets 1 so that the recorder misses nothing);
    ``discovery_timeout`` (s, 20): the bound on that wait.
    """

    def __init__(self, name: str):
        super().__init__(name, automatically_declare_parameters_from_overrides=True,
                         allow_undeclared_parameters=True)
        self.params = node_parameters(self, name)
        self.mech = mechanism_from_params(self.params)
        self.wait_for_subscribers = int(self.param('wait_for_subscribers', 0))
        self.discovery_timeout = self.positive('discovery_timeout', 20.0)
        self.health = Health(self, name)
        self._executor = None       # made on first use: see executor_
        self.data_publishers = []
        self.started = False        # diagnostics wait for the peers, like the data
        self.create_timer(1.0, self.report)

    @property
    def executor_(self) -> SingleThreadedExecutor:
        """This node's executor, made on first use, after the constructor: a
        constructor that raises (a parameter error) leaves no executor whose
        __del__ would print a traceback after rclpy has shut down."""
        if self._executor is None:
            self._executor = SingleThreadedExecutor()
            self._executor.add_node(self)
        return self._executor

    # -- parameters ---------------------------------------------------------
    def param(self, name, default):
        return self.params.get(name, default)

    def positive(self, name, default) -> float:
        try:
            value = float(self.param(name, default))
        except (TypeError, ValueError):
            raise ParameterError(name, 'expected a number, got %r' % self.param(name, default))
        if not value > 0 or value == float('inf'):
            raise ParameterError(name, 'must be a positive finite number, got %r' % value)
        return value

    # -- start-up -----------------------------------------------------------
    def publisher(self, msg_type, topic, qos):
        pub = self.create_publisher(msg_type, topic, qos)
        self.data_publishers.append(pub)
        return pub

    def wait_for_matches(self, extra=None) -> bool:
        """Bounded wait until the configured subscribers (and ``extra()``) are matched."""
        need = self.wait_for_subscribers
        pubs = self.data_publishers + [self.health.pub]

        def ready():
            ok = all(p.get_subscription_count() >= need for p in pubs)
            return ok and (extra is None or extra())
        start = time.monotonic()
        ok = wait_until(self, self.executor_, ready, self.discovery_timeout)
        self.started = True
        if ok:
            self.get_logger().info('matched after %.2f s' % (time.monotonic() - start))
        else:
            self.get_logger().warn('discovery: not all peers matched after %.1f s; starting anyway'
                                   % self.discovery_timeout)
            self.health.warning = 'started before all subscribers matched'
        return ok

    def report(self):
        if self.started:
            self.health.report()

    def run(self):
        self.wait_for_matches()
        self.executor_.spin()

    def run_on(self, subscription, service_period: float = 0.005):
        """Serve ``subscription`` directly (see DirectTake); the executor gets
        a turn every ``service_period`` seconds for timers and other topics."""
        import rclpy
        self.wait_for_matches()
        direct = DirectTake(self, subscription)
        next_service = 0.0
        while rclpy.ok():
            now = time.monotonic()
            if now >= next_service:
                self.executor_.spin_once(timeout_sec=0)
                next_service = now + service_period
            direct.poll(service_period)

    def flush(self, timeout: float = 2.0) -> None:
        """Let reliable subscribers (the recorder) receive everything before exiting."""
        from rclpy.duration import Duration
        for pub in self.data_publishers + [self.health.pub]:
            try:
                pub.wait_for_all_acked(Duration(seconds=timeout))
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass

    def close(self):
        self.report()
        self.flush()
