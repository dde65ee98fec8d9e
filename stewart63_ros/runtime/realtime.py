"""Operating-system knobs for a 1 kHz loop: real-time scheduling and timer slack."""
from __future__ import annotations

import ctypes
import os


def realtime_scheduling(priority: int) -> str:
    """SCHED_FIFO at ``priority`` (1-99) for every thread of this process,
    the middleware's included; threads started later inherit it. Returns ''
    or why it was refused (it needs root or CAP_SYS_NICE / an rtprio limit);
    nothing is changed then. Linux keeps 5 % of each second for other tasks
    (sched_rt_runtime_us), so a loop that never blocks cannot freeze the host.
    """
    try:
        param = os.sched_param(int(priority))
        main = os.getpid()
        os.sched_setscheduler(main, os.SCHED_FIFO, param)
        for tid in (int(t) for t in os.listdir('/proc/self/task')):
            if tid == main:
                continue
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            except ProcessLookupError:      # a thread that has just ended
                pass
    except (OSError, AttributeError, ValueError) as exc:
        return str(exc) or type(exc).__name__
    return ''


def reduce_timer_slack(slack_ns: int = 1000) -> bool:
    """Set this thread's timer slack (Linux; inherited by threads it starts).

    The kernel lets a timed wait of a normal thread overrun by its timer
    slack, 50 us by default: every ``WaitSet.wait`` with a timeout (even 0,
    which DDS turns into a futex wait with a deadline of now) then costs
    50 us more, and a 1 kHz loop wakes up to 50 us late. Called before
    rclpy starts, so the middleware's threads inherit it. Harmless elsewhere
    (returns False).
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, int(slack_ns), 0, 0, 0) == 0   # PR_SET_TIMERSLACK
    except (OSError, AttributeError, TypeError):
        return False
