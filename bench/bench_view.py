"""Does the live 3D view slow the realtime loop? Prints figures, asserts nothing.

Runs the realtime 1 kHz rig (plant + controller + fk, separate processes) in
turn without and with the view open, ``--repeat`` times each, so a busy
spell of the machine hits both alike:

- ``none``: the rig alone;
- ``server``: ``view`` serving the rig with a client connected that takes the
  scene updates but draws nothing (the view process's own cost: its
  subscriptions and its 30 Hz pushes over the websocket);
- ``browser``: ``view`` with the page open in headless Chromium, drawing the
  scene with software WebGL on the same two cores (the worst case: a real
  set-up draws the page on another machine or on a GPU).

Per variant: the median and the spread (min..max) of latency p50 / p99 and
of the missed-cycle fraction.

    bench_view.py [--duration S] [--repeat N] [--variants none,server,browser]
"""
from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import viser
from websockets.sync.client import connect

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import bench_loop  # noqa: E402

CHROMIUM = '/usr/bin/chromium'
CHROMIUM_ARGS = ['--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader',
                 '--disable-background-networking', '--disable-component-update',
                 '--disable-sync']
VARIANTS = ('none', 'server', 'browser')


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class View:
    """A ``view`` process on the bench's domain, and its URL once it serves."""

    def __init__(self, log_dir: Path):
        port = free_port()
        self.log = open(log_dir / 'view.log', 'w')
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'stewart63_ros.tools.view', '--port', str(port)],
            stdout=self.log, stderr=subprocess.STDOUT)
        self.url = None
        deadline = time.monotonic() + 120
        while self.url is None:
            for line in (log_dir / 'view.log').read_text().splitlines():
                if line.startswith('view: http'):
                    self.url = line.split()[1]
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError('view did not start: %s'
                                   % (log_dir / 'view.log').read_text()[-500:])
            time.sleep(0.1)

    def stop(self):
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class Client:
    """What looks at the page: Chromium drawing it, or a bare websocket
    client that reads every update viser pushes and draws nothing."""

    def __init__(self, url: str, draw: bool, profile: Path):
        self.draw = draw
        self.received = 0
        if draw:
            # lazy: optional (a test dependency): playwright costs 78 ms
            from playwright.sync_api import sync_playwright
            self._pw = sync_playwright().start()
            self.ctx = self._pw.chromium.launch_persistent_context(
                str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS,
                viewport={'width': 900, 'height': 600})
            self.page = self.ctx.new_page()
            self.page.goto(url, timeout=150_000)
            self.page.wait_for_selector('canvas', timeout=150_000)
        else:
            self.ws = connect(url.replace('http://', 'ws://'),
                              subprotocols=[_viser_subprotocol()])
            self._reader = threading.Thread(target=self._read, daemon=True)
            self._reader.start()

    def _read(self):
        try:
            for _ in self.ws:
                self.received += 1
        except Exception:  # noqa: BLE001 - the connection closed: reading ends
            pass

    def close(self):
        if self.draw:
            self.ctx.close()
            self._pw.stop()
        else:
            self.ws.close()


def _viser_subprotocol() -> str:
    """The websocket subprotocol viser's server requires (its version tag)."""
    return 'viser-v' + viser.__version__


def one_run(variant: str, duration: float, tmp: Path) -> dict | None:
    view = client = None
    try:
        if variant != 'none':
            view = View(tmp)
            client = Client(view.url, variant == 'browser', tmp / 'profile')
            time.sleep(3.0)      # the page's first frames drawn before the run starts
        s = bench_loop.run('realtime', duration, bench_loop.FULL)
        figures = bench_loop.realtime_figures(s) if s else None
        if figures is not None and client is not None and not client.draw:
            figures['updates'] = client.received
        return figures
    finally:
        if client is not None:
            client.close()
        if view is not None:
            view.stop()


def figure(runs, key, scale=1.0, form='%.0f') -> str:
    return bench_loop.spread([r[key] * scale for r in runs], form)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--duration', type=float, default=10.0, help='simulated s per run')
    parser.add_argument('--repeat', type=int, default=3, help='runs of each variant')
    parser.add_argument('--variants', default=','.join(VARIANTS),
                        help='comma-separated, of %s' % ', '.join(VARIANTS))
    args = parser.parse_args()
    variants = args.variants.split(',')
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error('unknown variants %s' % ', '.join(unknown))
    domain, fd = bench_loop.lease_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    runs = {v: [] for v in variants}
    try:
        for k in range(args.repeat):
            for variant in variants:
                with tempfile.TemporaryDirectory(prefix='bench_view_') as tmp:
                    f = one_run(variant, args.duration, Path(tmp))
                if f is None:
                    print('%-8s run %d failed' % (variant, k + 1), flush=True)
                    continue
                runs[variant].append(f)
                print('%-8s run %d: p50 %.0f us, p99 %.0f us, missed %.3f %%%s'
                      % (variant, k + 1, f['p50_us'], f['p99_us'], 100 * f['missed_fraction'],
                         ', %d websocket messages' % f['updates'] if 'updates' in f else ''),
                      flush=True)
    finally:
        os.close(fd)
    print('\nrealtime 1 kHz rig, %g s runs, median (min..max) of %d:' % (args.duration,
                                                                          args.repeat))
    for variant in variants:
        r = runs[variant]
        print('  %-8s p50 %s us   p99 %s us   missed %s %%'
              % (variant, figure(r, 'p50_us'), figure(r, 'p99_us'),
                 figure(r, 'missed_fraction', 100.0, '%.3f')))


if __name__ == '__main__':
    main()
