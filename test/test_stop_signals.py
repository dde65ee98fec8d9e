"""The one stop-signal handler (``launcher.StopSignals``) as each process uses it.

In this process, with real signals and no DDS: a node's (the first signal
interrupts once and starts the stop deadline), ``rig``'s (not before its
options are read, no deadline), and ``record``'s and ``play``'s (every signal
asks for the stop, none interrupts; ``play`` puts the previous handlers back).
The stop deadline is replaced by a counter: armed for real it would end the
test process 3.5 s later.
"""
from __future__ import annotations

import faulthandler
import signal

import pytest

from stewart63_ros.runtime import launcher
from stewart63_ros.runtime.launcher import StopSignals


@pytest.fixture
def deadlines(monkeypatch):
    """The stop deadlines armed (a list, one entry each), none for real; the
    test's handlers are put back afterwards."""
    armed = []
    monkeypatch.setattr(launcher, 'arm_stop_deadline', lambda: armed.append(True))
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield armed
    for sig, handler in before.items():
        signal.signal(sig, handler)
    faulthandler.cancel_dump_traceback_later()


def test_a_node_is_interrupted_by_the_first_signal_only(deadlines):
    signals = StopSignals(deadline=True, interrupt=True).install()
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)
    # Ctrl-C forwarded by a launcher, then its SIGTERM: only noted.
    signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGTERM)
    assert signals.requested
    assert signals.received == ['SIGINT', 'SIGINT', 'SIGTERM']
    assert deadlines == [True]


def test_a_node_in_its_hot_loop_is_not_interrupted(deadlines):
    signals = StopSignals(deadline=True, interrupt=True).install()
    signals.interruptible = False       # what RigNode.start_hot_loop does
    signal.raise_signal(signal.SIGTERM)
    assert signals.requested and deadlines == [True]


def test_rig_interrupts_for_a_signal_that_came_while_its_options_were_read(deadlines):
    signals = StopSignals(deadline=False, interrupt=False).install()
    signal.raise_signal(signal.SIGTERM)         # noted, nothing started yet
    with pytest.raises(KeyboardInterrupt):
        signals.interrupt_from_now()
    signal.raise_signal(signal.SIGINT)          # while the rig stops its nodes
    assert signals.received == ['SIGTERM', 'SIGINT']
    assert deadlines == []                      # Rig.stop takes longer than it


def test_rig_is_interrupted_once_after_its_options_are_read(deadlines):
    signals = StopSignals(deadline=False, interrupt=False).install()
    signals.interrupt_from_now()
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGTERM)
    assert signals.received[0] == 'SIGINT' and deadlines == []


@pytest.fixture(autouse=True)
def private_recorder_notes(monkeypatch, tmp_path):
    """A fake recorder's note for starting nodes goes to this test's folder,
    not to the machine's, where another test's nodes would wait for it."""
    from stewart63_ros.runtime import recorders
    monkeypatch.setattr(recorders, 'notes_dir', lambda: tmp_path / 'recorder_notes')


class FakeRecorder:
    """``record``'s Recorder without DDS: a signal while recording and
    another while the bag is closed."""

    topics = ['/leg_lengths']
    full_name = '/record'     # what record notes for starting nodes (runtime/recorders)
    domain_id = 0

    def __init__(self, *args, **kwargs):
        self.stop_requests = 0
        self.closed = False

    def open(self):
        pass

    def run(self, duration=None, stop_event=None):
        signal.raise_signal(signal.SIGINT)
        assert stop_event.is_set()

    def request_stop(self):
        self.stop_requests += 1
        if self.closed:
            raise RuntimeError('closed')

    def close(self):
        if not self.closed:
            self.closed = True
            signal.raise_signal(signal.SIGTERM)

    def summary(self):
        return 'record: fake'


def test_record_asks_for_the_stop_on_every_signal_and_exits_0(deadlines, monkeypatch, tmp_path):
    from stewart63_ros.recording import recorder
    from stewart63_ros.tools import record
    made = []
    monkeypatch.setattr(recorder, 'Recorder',       # record's main imports it from there
                        lambda *a, **k: made.append(FakeRecorder()) or made[-1])
    try:
        assert record.main([str(tmp_path / 'bag')]) == 0
    finally:
        faulthandler.unregister(signal.SIGUSR1)
    assert made[0].stop_requests == 2
    assert deadlines == [True]
    # From its end on, the process ignores them (its interpreter finalizes).
    assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN


class FakePlayer:
    """``play``'s Player without DDS: a signal while playing, another while
    it waits for the subscribers' acknowledgements at its close."""

    def __init__(self, *args, **kwargs):
        self.stop_requests = 0
        self.closes = 0

    def open(self):
        pass

    def wait_for_subscribers(self, count, timeout):
        return True

    def run(self):
        signal.raise_signal(signal.SIGINT)
        assert self.stop_requests == 1

    def request_stop(self):
        self.stop_requests += 1

    def close(self, ack_timeout=5.0):
        self.closes += 1
        if self.closes == 1:
            signal.raise_signal(signal.SIGTERM)

    def summary(self):
        return 'play: fake'


def test_play_stops_on_a_second_signal_too_and_puts_the_handlers_back(deadlines, monkeypatch):
    from stewart63_ros.tools import play
    made = []
    monkeypatch.setattr(play, 'Player', lambda *a, **k: made.append(FakePlayer()) or made[-1])

    def mine(signum, frame):
        raise AssertionError('the handler play replaced, called')
    signal.signal(signal.SIGINT, mine)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    assert play.main(['some_bag']) == 0
    assert made[0].stop_requests == 2
    assert deadlines == []          # a test may run it in its own process
    assert signal.getsignal(signal.SIGINT) is mine
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


class RecorderMadeAfterTheSignal(FakeRecorder):
    """Notes whether the stop was asked for before its recording began."""

    def run(self, duration=None, stop_event=None):
        self.stopped_before_run = stop_event.is_set()

    def close(self):
        self.closed = True


def test_record_stopped_before_its_recorder_exists_records_nothing_and_exits_0(
        deadlines, monkeypatch, tmp_path):
    """A signal while ``record`` still loads its modules (before the Recorder
    exists) is kept: the recorder, once made, stops at once, exit 0."""
    from stewart63_ros.recording import recorder
    from stewart63_ros.tools import record
    made = []

    def make(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)      # before the Recorder is returned
        made.append(RecorderMadeAfterTheSignal())
        return made[-1]
    monkeypatch.setattr(recorder, 'Recorder', make)
    try:
        assert record.main([str(tmp_path / 'bag')]) == 0
    finally:
        faulthandler.unregister(signal.SIGUSR1)
    assert made[0].stopped_before_run and made[0].closed
    assert deadlines == [True]
