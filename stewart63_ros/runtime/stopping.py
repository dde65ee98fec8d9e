"""A stopping node's flush: its last messages reach the recorder before it exits."""
from __future__ import annotations

import time

from rclpy.duration import Duration


class Flush:
    """``flush(timeout)`` for a RigNode (see its ``close``)."""

    #: s: how often flush looks at the acknowledgements and confirmations
    POLL = 0.005

    def __init__(self, node, word):
        self.node = node
        self.word = word            # handshake.RecorderWord
        #: called while flush waits: a recorder in the same thread takes its messages
        self.while_flushing = None

    def flush(self, timeout: float = 2.0) -> str:
        """Let reliable subscribers (the recorder) receive everything before exiting.

        Done when the package's recorder confirms on /diagnostics that it
        holds every message the node's last status says it published (a few
        ms after that status), or when every subscriber has acknowledged
        everything, or at ``timeout``. The acknowledgements alone can be
        slow (a subscriber acknowledges at the writer's next heartbeat), and
        a stop must stay well inside a launcher's 5 s.

        Args:
            timeout: s, the bound.

        Returns:
            How it ended: ``recorder``, ``acknowledged`` or ``timeout``.
        """
        deadline = time.monotonic() + timeout
        now_ = Duration(seconds=0)

        def unacked(pub):
            try:
                return pub.get_subscription_count() > 0 and not pub.wait_for_all_acked(now_)
            except RuntimeError:     # a publisher already destroyed: nothing left to send
                return False
        node = self.node
        pending = [p for p in node.data_publishers + [node.health.pub] if unacked(p)]
        while pending:
            if self.word.confirmed:
                return 'recorder'
            if time.monotonic() >= deadline:
                return 'timeout'
            if self.while_flushing is not None:
                self.while_flushing()
            time.sleep(self.POLL)
            self.word.take_waiting()    # the confirmation: no executor turns now
            pending = [p for p in pending if unacked(p)]
        return 'acknowledged'
