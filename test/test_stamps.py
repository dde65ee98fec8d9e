"""core/plumbing/stamps.py: the sample spacing check (a node given another rate than
the plant's), on stamps as the plant makes them: exact in lockstep, to a few
hundred ns in realtime, with missed cycles and a new run."""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.plumbing.stamps import SampleSpacing

MS = 1_000_000


def spacing_of(stamps, period_ns):
    check = SampleSpacing(period_ns)
    return [m for m in (check.add(int(ns)) for ns in stamps) if m]


def test_the_plants_period_is_no_news():
    assert spacing_of(np.arange(50) * MS, MS) == []                       # lockstep
    rng = np.random.default_rng(3)
    wall = 1_795_000_000 * 10**9 + np.arange(50) * MS + rng.integers(-400, 400, 50)
    wall = np.delete(wall, [5, 6, 7, 30])                                 # missed cycles
    assert spacing_of(wall, MS) == []
    # a new run (a reset): stamps from 0 again, no negative gap counted
    assert spacing_of(list(np.arange(8) * MS) + list(np.arange(8) * MS), MS) == []


def test_another_rate_is_named_once_with_both_periods():
    said = spacing_of(np.arange(50) * 5 * MS, MS)      # a 200 Hz plant, a 1 kHz node
    assert said == ["the samples come 5 ms apart, but sensor_rate 1000 Hz says 1 ms: give "
                    "this node the plant's sensor_rate (200 Hz), or its sample numbers are "
                    "wrong"]
    assert len(spacing_of(np.arange(50) * MS, 2 * MS)) == 1   # and the other way round


def test_it_judges_after_ten_gaps_and_not_before():
    check = SampleSpacing(MS)
    assert [check.add(k * 2 * MS) for k in range(10)] == [''] * 10        # nine gaps
    assert check.add(20 * MS).startswith('the samples come 2 ms apart')
