"""``plot --animate``: a GIF of the platform beside the leg lengths."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stewart63_ros.core.mechanics.kinematics import leg_lengths
from stewart63_ros.core.plumbing.params import load_mechanism
from stewart63_ros.core.plumbing.trajectory import COLUMNS, write_csv

REPO = Path(__file__).resolve().parents[1]
#: every test here spawns a process (view, rig, plot, a browser)
pytestmark = pytest.mark.slow


def rising_csv(path, mech, seconds=1.0, rate=50):
    """A trajectory CSV of the platform rising 15 cm, lengths by inverse kinematics."""
    rows = []
    for t in np.arange(0, seconds + 1e-9, 1.0 / rate):
        position = np.array([0.0, 0.0, 1.0 + 0.15 * t / seconds])
        row = dict.fromkeys(COLUMNS, 0.0)
        row.update(t=t, x=0.0, y=0.0, z=position[2])
        for i, L in enumerate(leg_lengths(mech, position, np.eye(3))):
            row['L%d' % (i + 1)] = L
            row['F%d' % (i + 1)] = 500.0 * i
        rows.append([row[c] for c in COLUMNS])
    write_csv(path, np.array(rows))
    return path


def test_plot_animate_writes_a_gif_that_moves(tmp_path):
    from PIL import Image
    mech = load_mechanism(REPO / 'config' / 'stewart63.yaml')
    csv = rising_csv(tmp_path / 'trajectory.csv', mech)
    out = tmp_path / 'run.gif'
    result = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.plot', '--animate',
                             str(csv), '--out', str(out), '--fps', '10'],
                            capture_output=True, text=True, timeout=300, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert str(out) in result.stdout
    gif = Image.open(out)
    assert gif.n_frames == 11                      # 1 s at 10 fps, both ends
    gif.seek(0)
    first = np.asarray(gif.convert('RGB')).astype(int)
    gif.seek(gif.n_frames - 1)
    last = np.asarray(gif.convert('RGB')).astype(int)
    assert first.std() > 10
    w = first.shape[1]
    # both halves change: the platform (left) and the cursor (right)
    assert (np.abs(first[:, :w // 2] - last[:, :w // 2]).sum(axis=2) > 60).sum() > 100
    assert (np.abs(first[:, w // 2:] - last[:, w // 2:]).sum(axis=2) > 60).sum() > 20


def test_plot_animate_refuses_another_format(tmp_path):
    mech = load_mechanism(REPO / 'config' / 'stewart63.yaml')
    csv = rising_csv(tmp_path / 'trajectory.csv', mech, seconds=0.2)
    result = subprocess.run([sys.executable, '-m', 'stewart63_ros.tools.plot', '--animate',
                             str(csv), '--out', str(tmp_path / 'x.avi')],
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 2
    assert '.gif' in result.stderr and 'Traceback' not in result.stderr
