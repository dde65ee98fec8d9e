"""`plot`: the paper's Fig. 4 (leg lengths, position, orientation against time).

    plot SOURCE [--out FILE.png]

SOURCE is a trajectory CSV or a rosbag2 directory recorded from the rig
(docs/interface.md: "Trajectory CSV", "Bags").
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def draw_figure(columns: dict, out_path, title: str = '') -> Path:
    """Write Fig. 4 from {column: array} (the CSV layout) to ``out_path``."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    t = columns['t']
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for i in range(1, 7):
        axes[0].plot(t, columns['L%d' % i], label='$L_%d$' % i)
    axes[0].set_ylabel('leg length [m]')
    for name, label in (('x', '$t_x$'), ('y', '$t_y$'), ('z', '$t_z$')):
        axes[1].plot(t, columns[name], label=label)
    axes[1].set_ylabel('position [m]')
    for name, label in (('theta_x', r'$\theta_x$'), ('theta_y', r'$\theta_y$'),
                        ('theta_z', r'$\theta_z$')):
        axes[2].plot(t, columns[name], label=label)
    axes[2].set_ylabel('orientation [rad]')
    axes[2].set_xlabel('time [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='best', fontsize='small', ncol=3)
    fig.suptitle(title or '6-3 Stewart platform, PD control (Yurt & Ozkol, Fig. 4)')
    fig.tight_layout()
    out_path = Path(out_path)
    fig.savefig(out_path, dpi=100)
    plt.close(fig)
    return out_path


def load_columns(source) -> dict:
    """Trajectory columns from a CSV file or a bag directory."""
    source = Path(source)
    if source.is_dir():
        from stewart63_ros.bagio import trajectory_from_bag
        return trajectory_from_bag(source)
    from stewart63_ros.core.trajectory import read_csv
    return read_csv(source)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='plot', description=__doc__.split('\n\n')[0])
    parser.add_argument('source', help='trajectory CSV or rosbag2 directory')
    parser.add_argument('--out', help='PNG to write (default: figure.png beside the source)')
    args = parser.parse_args(argv)
    source = Path(args.source)
    if not source.exists():
        parser.exit(2, 'plot: error: %s does not exist\n' % source)
    try:
        columns = load_columns(source)
    except (ValueError, OSError) as exc:  # TrajectoryError, BagError
        parser.exit(2, 'plot: error: %s\n' % exc)
    if len(columns['t']) == 0 or not np.all(np.isfinite(columns['t'])):
        parser.exit(2, 'plot: error: %s holds no samples\n' % source)
    out = Path(args.out) if args.out else (
        source / 'figure.png' if source.is_dir() else source.with_name('figure.png'))
    draw_figure(columns, out, title=source.name)
    print(out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
