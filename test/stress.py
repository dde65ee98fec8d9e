"""The test suite, round after round, while another process keeps a core busy.

    python test/stress.py [--rounds 3] [--busy 1] -- PYTEST_ARGS...

``make test-stress`` runs the DDS tests three times in a row this way. It
stops at the first red round and exits with pytest's status; every round's
result and wall time are printed. The busy processes are plain Python loops,
stopped however the run ends.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='stress', description=__doc__.split('\n\n')[0])
    parser.add_argument('--rounds', type=int, default=3, help='rounds in a row (3)')
    parser.add_argument('--busy', type=int, default=1, help='cores kept busy (1)')
    parser.add_argument('pytest_args', nargs='*', help='after --: what pytest runs')
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.busy < 0:
        parser.error('--rounds must be >= 1 and --busy >= 0')
    busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
            for _ in range(args.busy)]
    results = []
    code = 0
    try:
        for k in range(1, args.rounds + 1):
            start = time.monotonic()
            print('stress: round %d of %d, %d core(s) kept busy: pytest %s'
                  % (k, args.rounds, args.busy, ' '.join(args.pytest_args)), flush=True)
            code = subprocess.call([sys.executable, '-m', 'pytest', '-q', *args.pytest_args])
            results.append((k, code, time.monotonic() - start))
            print('stress: round %d %s in %.0f s' % (k, 'green' if code == 0 else 'RED (exit %d)'
                                                     % code, results[-1][2]), flush=True)
            if code != 0:
                break
    finally:
        for proc in busy:
            proc.kill()
            proc.wait(10)
    green = sum(1 for _, c, _ in results if c == 0)
    print('stress: %d of %d rounds green in a row%s' % (
        green, args.rounds, '' if code == 0 else '; stopped at the first red one'))
    return code


if __name__ == '__main__':
    sys.exit(main())
