"""A source that starts again, and two sources on one topic.

- StampGate (no DDS): a new publisher after a pause, or stamps jumping back
  after a pause, start a new run (accepted, counted); out-of-order samples
  within a run and a second publisher interleaving are refused.
- Over DDS: a lockstep plant run twice (and a realtime one restarted) under
  one running controller is answered in full the second time; ``play`` of one
  bag twice into a running fk: the second replay is answered in full; two rigs
  in one domain under one namespace report the collision on /diagnostics
  within a second, naming the publishers, and their controllers withhold
  forces.
"""
from __future__ import annotations

import pytest

from stewart63_ros.nodes.checks import Rejected, StampGate

A, B = b'A' * 16, b'B' * 16


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def feed(gate, ns, source):
    ns = gate.check_ns(ns, source)
    gate.check_source(source)
    gate.accept(ns, source)
    return gate.new_run


def test_gate_new_publisher_after_a_pause_is_a_new_run():
    clock = Clock()
    gate = StampGate(0.5, clock)
    for k in range(10):
        clock.t += 0.001
        assert feed(gate, 10**9 + k * 10**6, A) == ''
    clock.t += 2.0                        # the plant ended; a new one starts from 0
    assert feed(gate, 0, B) == 'a new publisher'
    assert gate.restarts == 1
    clock.t += 0.001
    assert feed(gate, 10**6, B) == ''
    with pytest.raises(Rejected) as exc:  # within the new run: order still holds
        clock.t += 0.001
        gate.check_ns(0, B)
    assert exc.value.reason == 'stamp_from_past'
    assert gate.restarts == 1


def test_gate_same_publisher_jumping_back_after_a_pause_is_a_new_run():
    clock = Clock()
    gate = StampGate(0.5, clock)
    feed(gate, 5 * 10**9, A)
    clock.t += 0.1                        # no pause: refused
    with pytest.raises(Rejected) as exc:
        gate.check_ns(10**9, A)
    assert exc.value.reason == 'stamp_from_past'
    clock.t += 0.6                        # quiet for 0.7 s, then back to 1 s: a new run
    assert feed(gate, 10**9, None).startswith('stamps jumped back')
    assert gate.restarts == 1


def test_gate_without_restart_pause_refuses_every_older_stamp():
    clock = Clock()
    gate = StampGate(None, clock)
    feed(gate, 5 * 10**9, A)
    clock.t += 100.0
    with pytest.raises(Rejected):
        gate.check_ns(10**9, B)


def test_gate_second_publisher_interleaving_is_refused_and_counted():
    clock = Clock()
    gate = StampGate(0.5, clock)
    refused = 0
    for k in range(100):                  # two rigs: both send at 1 kHz
        clock.t += 0.0005
        source = A if k % 2 == 0 else B
        try:
            feed(gate, 10**9 + k * 10**6, source)
        except Rejected as exc:
            assert exc.reason == 'second_source'
            refused += 1
    assert refused == 50 and gate.interleaved == 50 and gate.other_source == B
    assert gate.restarts == 0 and gate.source == A


def test_gate_bad_content_from_a_second_publisher_keeps_its_own_reason():
    """The source check comes after the content checks (see wire)."""
    import numpy as np

    from stewart63_ros.nodes import wire
    gate = StampGate(0.5)
    good = wire.JointStateTemplates(('effort',)).get('base')
    wire_ok = good.fill(1, 0, effort=np.ones(6))
    ns, *_ = wire.joint_state_sample(wire_ok, gate, ('effort',), source=A)
    gate.accept(ns, A)
    bad = good.fill(2, 0, effort=np.array([np.nan] + [1.0] * 5))
    with pytest.raises(Rejected) as exc:
        wire.joint_state_sample(bad, gate, ('effort',), source=B)
    assert exc.value.reason == 'non_finite'
    with pytest.raises(Rejected) as exc:
        wire.joint_state_sample(good.fill(2, 0, effort=np.ones(6)), gate, ('effort',), source=B)
    assert exc.value.reason == 'second_source'
