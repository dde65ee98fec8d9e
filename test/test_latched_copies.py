"""The copies of a latched sample through a topic's two subscriptions are
told from new samples (commands.LatchedCopies; no DDS): what CommandInput
and the recorder drop."""
from __future__ import annotations

from stewart63_ros.runtime import commands
from stewart63_ros.runtime.commands import DUPLICATE_WINDOW, LatchedCopies


def test_the_copy_through_the_other_subscription_is_dropped_once():
    copies = LatchedCopies()
    assert copies.first('volatile', b'x')
    assert not copies.first('latched', b'x')        # its copy
    assert copies.first('latched', b'x')            # published again: a new sample
    assert copies.first('volatile', b'y')


def test_a_sample_sent_twice_through_one_subscription_is_not_a_copy():
    copies = LatchedCopies()
    assert copies.first('volatile', b'x')
    assert copies.first('volatile', b'x')
    assert not copies.first('latched', b'x')
    assert not copies.first('latched', b'x')


def test_copies_of_samples_in_flight_together_are_all_dropped():
    copies = LatchedCopies()
    assert [copies.first(tag, data) for tag, data in (
        ('main', b'a'), ('main', b'b'), ('volatile', b'a'), ('volatile', b'b'))] \
        == [True, True, False, False]


def test_a_copy_later_than_the_window_is_a_new_sample(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(commands.time, 'monotonic', lambda: now[0])
    copies = LatchedCopies()
    assert copies.first('volatile', b'x')
    now[0] += DUPLICATE_WINDOW + 0.01
    assert copies.first('latched', b'x')
