"""What ``ros2 param list / describe / get`` show of each node, over DDS.

The nodes are started by hand from the packaged parameter file, as a ``ros2
run`` user does (``plant --ros-args --params-file config/stewart63.yaml``).
A client node then asks each one through the parameter services the real
``ros2 param`` CLI calls (``list_parameters``, ``describe_parameters``,
``get_parameters``, ``set_parameters``; the CLI itself is not installed in
CI). What they must show:

- every key the interface page documents for the node (the model's table,
  and each row of the node-specific table that names the node or "all"),
  given in the file or not, with its value (``faults`` an empty string list,
  not "not set");
- for each key its one declaration (core/plumbing/node_parameters.py): the unit in
  its description, its inclusive range, ``read_only`` for a key fixed at
  start-up, which rcl then refuses to set, with a reason;
- the packaged file's ``clock_mode`` on all three nodes.

Every wait is bounded; every process is stopped by its pid (the harness).
"""
from __future__ import annotations

import math
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PARAMS = REPO / 'config' / 'stewart63.yaml'
DOC = REPO / 'docs' / 'interface.md'
NODES = ('plant', 'controller', 'fk')
#: rcl_interfaces/msg/ParameterType
INTEGER, DOUBLE, STRING, DOUBLE_ARRAY, STRING_ARRAY = 2, 3, 4, 8, 9


def documented_keys(node: str) -> set[str]:
    """The keys docs/interface.md says ``node`` reads: the model's, and the
    node-specific rows whose "read by" names it or says "all"."""
    text = DOC.read_text()
    model = text[text.index('### The model (shared keys)'):text.index('### Node-specific keys')]
    keys = set(re.findall(r'^\| `([a-z_]+)` \|', model, re.M))
    own = text[text.index('### Node-specific keys'):text.index('## Control laws')]
    for key, readers in re.findall(r'^\| `([a-z_]+)` \| ([^|]*) \|', own, re.M):
        if readers.strip() == 'all' or node in [r.strip() for r in readers.split(',')]:
            keys.add(key)
    return keys


class Asker:
    """The test's client of one node's parameter services."""

    def __init__(self, ros, node_name: str):
        from rcl_interfaces.srv import (
            DescribeParameters,
            GetParameters,
            ListParameters,
            SetParameters,
        )
        self.ros = ros
        self.node = ros.node('asker_' + node_name.strip('/').replace('/', '_'))
        self.types = {'list': ListParameters, 'describe': DescribeParameters,
                      'get': GetParameters, 'set': SetParameters}
        self.clients = {what: self.node.create_client(srv, '%s/%s_parameters' % (
            node_name, what)) for what, srv in self.types.items()}

    def ready(self, timeout: float) -> bool:
        return all(c.wait_for_service(timeout_sec=timeout) for c in self.clients.values())

    def call(self, what, **fields):
        future = self.clients[what].call_async(self.types[what].Request(**fields))
        assert self.ros.spin_until(future.done, 30), 'no answer from %s' % what
        return future.result()

    def names(self) -> set[str]:
        return set(self.call('list').result.names)

    def describe(self, *names) -> dict:
        return {d.name: d for d in self.call('describe', names=list(names)).descriptors}

    def get(self, *names) -> dict:
        from rclpy.parameter import parameter_value_to_python
        values = self.call('get', names=list(names)).values
        return {n: (v.type, parameter_value_to_python(v)) for n, v in zip(names, values)}

    def set(self, name, value):
        from rclpy.parameter import Parameter
        result = self.call('set', parameters=[Parameter(name, value=value).to_parameter_msg()])
        return result.results[0].successful, result.results[0].reason


@pytest.fixture(scope='module')
def nodes(tmp_path_factory):
    """plant, controller and fk started by hand with the packaged file, each
    in its own namespace (no rig: nothing else sets their parameters)."""
    from ros_harness import RosTest, lease_domain_id
    ros = RosTest(lease_domain_id(), tmp_path_factory.mktemp('describe'))
    try:
        askers = {}
        for kind in NODES:
            exe = str(Path(sys.executable).parent / kind)
            ros.spawn([exe, '--ros-args', '--params-file', str(PARAMS),
                       '-r', '__ns:=/by_hand_%s' % kind], name=kind)
            askers[kind] = Asker(ros, '/by_hand_%s/%s' % (kind, kind))
        for asker in askers.values():
            assert asker.ready(120), ros.log_dir
        yield askers
    finally:
        ros.cleanup()


@pytest.mark.parametrize('kind', NODES)
def test_ros2_param_list_shows_every_documented_key(nodes, kind):
    documented = documented_keys(kind)
    assert {'sensor_noise', 'sensor_seed', 'endstop_stiffness'} <= documented_keys('plant')
    names = nodes[kind].names()
    assert documented <= names, sorted(documented - names)
    # and each one has a value (a key left out of the file: its default)
    values = nodes[kind].get(*sorted(documented))
    assert not [k for k, (kind_of, _) in values.items() if kind_of == 0], values


def test_the_plants_keys_left_out_of_the_file_have_their_defaults(nodes):
    values = nodes['plant'].get('faults', 'sensor_noise', 'sensor_seed', 'endstop_stiffness',
                                'lockstep_peers', 'step_count')
    assert values == {'faults': (STRING_ARRAY, []), 'sensor_noise': (DOUBLE, 0.0),
                      'sensor_seed': (INTEGER, 0), 'endstop_stiffness': (DOUBLE, 2.0e6),
                      'lockstep_peers': (STRING_ARRAY, []), 'step_count': (INTEGER, 1)}


def test_the_packaged_file_runs_every_node_in_one_clock_mode(nodes):
    modes = {kind: nodes[kind].get('clock_mode')['clock_mode'][1] for kind in NODES}
    assert modes == {'plant': 'lockstep', 'controller': 'lockstep', 'fk': 'lockstep'}
    # the controller's watchdog default follows it (2 s in lockstep)
    assert nodes['controller'].get('watchdog_timeout')['watchdog_timeout'] == (DOUBLE, 2.0)


def _range(descriptor):
    if descriptor.floating_point_range:
        r = descriptor.floating_point_range[0]
        return r.from_value, r.to_value
    if descriptor.integer_range:
        r = descriptor.integer_range[0]
        return r.from_value, r.to_value
    return None


@pytest.mark.parametrize('kind, key, type_, unit, range_, read_only', [
    ('plant', 'sensor_rate', DOUBLE, '[Hz]', (math.ulp(0.0), math.inf), True),
    ('plant', 'lockstep_window', INTEGER, '[samples]', (1, 900), True),
    ('plant', 'step_count', INTEGER, '[samples]', (1, 10**9), False),
    ('plant', 'faults', STRING_ARRAY, '[fault strings]', None, False),
    ('plant', 'sensor_noise', DOUBLE, '[m]', (0.0, math.inf), True),
    ('plant', 'platform_mass', DOUBLE, '[kg]', (math.ulp(0.0), math.inf), True),
    ('plant', 'kp', DOUBLE_ARRAY, '[N/m]', None, True),
    ('controller', 'kp', DOUBLE_ARRAY, '[N/m]', None, False),
    ('controller', 'ct_kd', DOUBLE_ARRAY, '[1/s]', None, False),
    ('controller', 'control_law', STRING, '', None, False),
    ('controller', 'watchdog_timeout', DOUBLE, '[s (wall clock)]', (math.ulp(0.0), math.inf),
     True),
    ('controller', 'realtime_priority', INTEGER, '', (0, 99), True),
    ('fk', 'marker_rate', DOUBLE, '[Hz]', (0.0, 200.0), True),
    ('fk', 'singularity_threshold', DOUBLE, '', (math.ulp(0.0), math.inf), True),
    ('fk', 'leg_length_max', DOUBLE, '[m]', (math.ulp(0.0), math.inf), True),
])
def test_ros2_param_describe_shows_unit_range_and_read_only(nodes, kind, key, type_, unit,
                                                              range_, read_only):
    from stewart63_ros.core.plumbing.node_parameters import describe
    d = nodes[kind].describe(key)[key]
    expected = describe(key, kind)
    # kp, ct_kp, ct_kd changeable at run time take integer lists too (dynamic typing)
    assert d.type == type_ or (d.dynamic_typing and not read_only), d
    assert unit in d.description and d.description == expected.description, d
    assert d.additional_constraints == expected.constraints and d.additional_constraints or \
        key == 'control_law', d
    assert _range(d) == range_, d
    assert d.read_only is read_only, d


def test_rcl_refuses_to_set_a_read_only_key_and_its_range_a_value_out_of_it(nodes):
    ok, reason = nodes['plant'].set('sensor_rate', 500.0)
    assert not ok and reason == 'Trying to set a read-only parameter: sensor_rate.', reason
    assert nodes['plant'].get('sensor_rate')['sensor_rate'] == (DOUBLE, 1000.0)
    ok, reason = nodes['plant'].set('step_count', 0)
    assert not ok and 'step_count' in reason, reason
    ok, reason = nodes['plant'].set('step_count', 3)
    assert ok, reason
    ok, reason = nodes['controller'].set('kp', [100, 200, 300, 400, 500, 600])
    assert ok, reason                       # integers, as `ros2 param set` reads [100, ...]
    ok, reason = nodes['fk'].set('kp', [1.0] * 6)
    assert not ok and 'read-only' in reason, reason
