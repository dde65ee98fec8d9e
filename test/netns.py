"""Two "hosts" on one machine: two network namespaces joined by a veth pair.

Needs root (``ip netns``); ``TwoHosts.available()`` says why not otherwise.
Names are unique per test run (pid and a counter), and ``close()`` deletes
both namespaces (the veth pair goes with them) whatever happened. Traffic
stays inside the namespaces made here: each has its own loopback and the
veth link, with a multicast route on the link for DDS discovery.
"""
from __future__ import annotations

import itertools
import os
import shutil
import subprocess

_counter = itertools.count()


def _ip(*args, check=True):
    return subprocess.run(['ip', *args], check=check, capture_output=True, text=True,
                          timeout=10)


class TwoHosts:
    """Namespaces ``a`` and ``b``; ``a_dev`` / ``b_dev`` their ends of the link."""

    def __init__(self):
        k = next(_counter)
        tag = '%d%d' % (os.getpid() % 100000, k)
        self.a, self.b = 's63%sa' % tag, 's63%sb' % tag
        self.a_dev, self.b_dev = ('v%sa' % tag)[:15], ('v%sb' % tag)[:15]
        net = '10.%d.%d' % (200 + os.getpid() % 50, k % 250)
        self.a_addr, self.b_addr = net + '.1', net + '.2'
        self.made = []

    @staticmethod
    def available() -> str:
        """'' if namespaces can be made here, else the reason they cannot."""
        if shutil.which('ip') is None:
            return 'no `ip` command (iproute2)'
        if os.geteuid() != 0:
            return 'network namespaces need root (ip netns)'
        return ''

    def open(self):
        try:
            for ns in (self.a, self.b):
                _ip('netns', 'add', ns)
                self.made.append(ns)
            _ip('link', 'add', self.a_dev, 'type', 'veth', 'peer', 'name', self.b_dev)
            for ns, dev, addr in ((self.a, self.a_dev, self.a_addr),
                                  (self.b, self.b_dev, self.b_addr)):
                _ip('link', 'set', dev, 'netns', ns)
                _ip('-n', ns, 'addr', 'add', addr + '/24', 'dev', dev)
                _ip('-n', ns, 'link', 'set', 'lo', 'up')
                _ip('-n', ns, 'link', 'set', dev, 'up')
                _ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)
        except BaseException:
            self.close()
            raise
        return self

    def exec_prefix(self, ns):
        return ['ip', 'netns', 'exec', ns]

    def link(self, up: bool):
        """Cut (False) or restore (True) the link, at host a's end."""
        _ip('-n', self.a, 'link', 'set', self.a_dev, 'up' if up else 'down')

    def close(self):
        for ns in self.made:
            _ip('netns', 'del', ns, check=False)
        self.made = []
        # a veth end not yet moved into a namespace
        _ip('link', 'del', self.a_dev, check=False)


def dds_env(base: dict) -> dict:
    """DDS between the namespaces: UDP only (no shared memory across hosts),
    discovery on the subnet."""
    env = dict(base)
    env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'
    return env
