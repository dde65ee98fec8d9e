"""bench/bench_floor.py: the floor figures docs/performance.md cites."""
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def test_bench_floor_prints_every_figure_and_every_message_between_processes_arrives():
    out = subprocess.run([sys.executable, str(ROOT / 'bench' / 'bench_floor.py'),
                          '--samples', '1000', '--repeat', '1', '--json'],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    figures = json.loads(out.stdout)
    for key in ('composed_dds_us', 'composed_dds_kernels_us', 'composed_dds_kernels_read_us',
                'kernels_alone_us', 'xproc_publish_cpu_us', 'xproc_take_cpu_us',
                'sleep_wake_cpu_us'):
        assert math.isfinite(figures[key]) and figures[key] > 0, (key, figures)
    # The per-take figure is per message received: none may be missing.
    assert figures['xproc_lost'] == 0
