"""`make demo`: the full rig on the paper's scenario, recorded, with Fig. 4.

Runs plant, controller, fk and the recorder as separate nodes over DDS
(lockstep, 1 kHz, 10 s of simulated time), composed into one process, the
fastest way that records every topic (``--separate``: one process per node,
as ``rig`` runs them by default); writes the bag and the figure drawn from
it, and prints the summary with the wall time beside the simulated time.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import sys
import time
from pathlib import Path

from stewart63_ros.paths import PACKAGED_GEOMETRIES, RIG_CLOCK_MODE, packaged_params_path
from stewart63_ros.tools import plot, rig


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', default='out/demo', help='folder for the run (out/demo)')
    parser.add_argument('--duration', type=float, default=10.0)
    parser.add_argument('--mode', choices=('lockstep', 'realtime'), default=RIG_CLOCK_MODE)
    parser.add_argument('--separate', action='store_true',
                        help='one process per node instead of one for all (slower)')
    parser.add_argument('--geometry', choices=tuple(PACKAGED_GEOMETRIES), default='6-3',
                        help="the packaged machine: 6-3, the paper's (config/stewart63.yaml), or "
                        '6-6, a lab hexapod (config/hexapod66.yaml); `make demo GEOMETRY=6-6`')
    args = parser.parse_args(argv)
    params = packaged_params_path(args.geometry)
    run_dir = Path(args.out) / time.strftime('run-%Y%m%d-%H%M%S')
    run_dir.mkdir(parents=True, exist_ok=False)
    bag = run_dir / 'bag'
    # A domain of its own, so the demo does not talk to another rig on this host.
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(120, 200)))
    print('demo: rig (%s, %s, %g s of the paper scenario on the %s, %s), recording into %s'
          % (args.mode, 'separate processes' if args.separate else 'nodes composed in one '
             'process', args.duration, args.geometry, params.name, bag), flush=True)
    started = time.monotonic()
    code = rig.main(['--params', str(params), '--mode', args.mode,
                     '--duration', str(args.duration), '--record', str(bag),
                     '--log-dir', str(run_dir / 'logs')]
                    + ([] if args.separate else ['--compose']))
    wall = time.monotonic() - started
    if code != 0:
        print('demo: the rig failed (exit %d); logs in %s' % (code, run_dir / 'logs'),
              file=sys.stderr)
        return code
    figure = run_dir / 'figure.png'
    plot.main([str(bag), '--out', str(figure), '--params', str(params)])
    loop = None
    try:
        loop = json.loads((run_dir / 'logs' / 'plant_summary.json').read_text())['wall_time_s']
    except (OSError, ValueError, KeyError):
        pass
    print('demo: %g s simulated in %.1f s wall, start-up included (%.2fx real time)%s'
          % (args.duration, wall, args.duration / wall,
             '; the loop alone %.1f s (%.2fx)' % (loop, args.duration / loop) if loop else ''))
    print('demo: bag    %s' % bag.resolve())
    print('demo: figure %s' % figure.resolve())
    print('demo: where to look:')
    print('  the run in 3D in a browser:   .venv/bin/view %s   then open '
          'http://localhost:8080/' % bag)
    print('  a live rig in the browser:    .venv/bin/rig --mode realtime --view')
    print('  an animation of the run:      .venv/bin/plot --animate %s' % bag)
    print('  RViz2 / Foxglove: the bag has the markers topic (docs/view.md)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
