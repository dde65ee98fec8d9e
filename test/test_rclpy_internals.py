"""The private rclpy calls of the 1 kHz loops (runtime/rclpy_internals.py).

These are not rclpy's public API: if a rclpy release changes them, this test
fails loudly, instead of a hot loop that quietly stops taking messages or
running its timers.
"""
import time

from sensor_msgs.msg import JointState

from stewart63_ros.runtime.rclpy_internals import (
    DirectTake,
    raw_publisher,
    run_timer_if_ready,
    take,
)


def test_take_direct_take_and_timers_work_in_this_rclpy(ros):
    node = ros.node('internals_probe')
    got = []
    sub = node.create_subscription(JointState, 'internals', got.append, 10, raw=True)
    pub = node.create_publisher(JointState, 'internals', 10)
    assert ros.spin_until(lambda: pub.get_subscription_count() >= 1, timeout=10)

    assert take(sub) is None                      # nothing yet: None, no exception
    pub.publish(JointState(name=['a']))
    deadline = time.monotonic() + 5
    data = None
    while data is None and time.monotonic() < deadline:
        data = take(sub)
    assert isinstance(data, bytes) and len(data) > 8   # raw: the serialized bytes

    direct = DirectTake(node, sub)
    assert direct.poll(0.0) is False               # empty: returns at once
    pub.publish(JointState(name=['b']))
    assert direct.poll(5.0) is True                # waits in its own wait set
    assert len(got) == 1 and isinstance(got[0], bytes)

    send = raw_publisher(pub)                      # serialized bytes, as they are
    send(got[0])
    assert direct.poll(5.0) is True
    assert len(got) == 2 and got[1] == got[0]

    calls = []
    timer = node.create_timer(0.01, lambda: calls.append(1))
    deadline = time.monotonic() + 5
    while not calls and time.monotonic() < deadline:
        run_timer_if_ready(timer)
        time.sleep(0.002)
    assert calls, 'a due timer must run'
    ran = run_timer_if_ready(timer)                # just ran: its next period started
    assert ran is False and len(calls) == 1
    timer.destroy()
    assert run_timer_if_ready(timer) is False      # destroyed: skipped, no exception


def test_wait_any_wakes_on_any_of_its_subscriptions(ros):
    from stewart63_ros.runtime.rclpy_internals import WaitAny
    node = ros.node('wait_any_probe')
    subs = [node.create_subscription(JointState, 'wait_any_%d' % i, lambda m: None, 10,
                                     raw=True) for i in range(2)]
    pub = node.create_publisher(JointState, 'wait_any_1', 10)
    assert ros.spin_until(lambda: pub.get_subscription_count() >= 1, timeout=10)
    waiter = WaitAny(node.context, subs)
    t0 = time.monotonic()
    waiter.wait(0.05)                              # nothing: returns after the timeout
    assert time.monotonic() - t0 >= 0.04
    pub.publish(JointState(name=['c']))
    t0 = time.monotonic()
    waiter.wait(5.0)                               # the second one has a message
    assert time.monotonic() - t0 < 4.0
    assert take(subs[1]) is not None and take(subs[0]) is None


def test_wait_any_wakes_on_a_guard_condition_and_take_with_info_gives_the_info(ros):
    """The recorder's wait: its subscriptions plus a guard condition (its stop)."""
    from stewart63_ros.runtime.rclpy_internals import WaitAny, take_with_info
    node = ros.node('guard_probe')
    sub = node.create_subscription(JointState, 'guarded', lambda _m: None, 10, raw=True)
    pub = node.create_publisher(JointState, 'guarded', 10)
    assert ros.spin_until(lambda: pub.get_subscription_count() >= 1, timeout=10)
    guard = node.create_guard_condition(lambda: None)
    waiter = WaitAny(node.context, [sub], [guard])
    guard.trigger()
    start = time.monotonic()
    waiter.wait(5.0)
    assert time.monotonic() - start < 2.5, 'a triggered guard condition must end the wait'
    pub.publish(JointState(name=['c']))
    waiter.wait(5.0)
    taken = take_with_info(sub)
    assert taken is not None
    data, info = taken
    assert isinstance(data, bytes) and info['received_timestamp'] > 0
