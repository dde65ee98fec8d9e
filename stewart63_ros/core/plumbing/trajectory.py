"""The trajectory CSV (docs/interface.md): one layout for `sim` and `plot`."""
from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

COLUMNS = (['t', 'x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z',
            'vx', 'vy', 'vz', 'wx', 'wy', 'wz']
           + ['L%d' % i for i in range(1, 7)]
           + ['Ldot%d' % i for i in range(1, 7)]
           + ['F%d' % i for i in range(1, 7)])


class TrajectoryError(ValueError):
    """A file that is not a trajectory CSV."""


def write_csv(path: str | os.PathLike, table: np.ndarray) -> None:
    """Write a trajectory CSV: the header, then the rows as repr-exact floats.

    Args:
        path: the file (overwritten).
        table: (N, len(COLUMNS)) rows in the order of ``COLUMNS``.

    Raises:
        TrajectoryError: a table of another shape.
    """
    table = np.asarray(table, float)
    if table.ndim != 2 or table.shape[1] != len(COLUMNS):
        raise TrajectoryError('expected an (N, %d) table, got %s' % (len(COLUMNS), table.shape))
    with open(path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(COLUMNS)
        # repr-exact floats so a reader gets the same doubles back
        writer.writerows([[repr(float(v)) for v in row] for row in table])


def read_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a trajectory CSV.

    Args:
        path: the file.

    Returns:
        {column name: (N,) array}, for every name of ``COLUMNS``.

    Raises:
        TrajectoryError: the file cannot be read, or is not a trajectory CSV
            (the message names the problem).
    """
    path = Path(path)
    try:
        with open(path, newline='') as stream:
            reader = csv.reader(stream)
            header = next(reader, None)
            rows = list(reader)
    except OSError as exc:
        raise TrajectoryError('cannot read %s: %s' % (path, exc.strerror)) from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise TrajectoryError('%s is not a trajectory CSV: %s' % (path, exc)) from None
    if header is None or [h.strip() for h in header] != COLUMNS:
        raise TrajectoryError('%s: header is not the trajectory layout (%s ...)'
                              % (path, ', '.join(COLUMNS[:4])))
    try:
        table = np.array(rows, dtype=float).reshape(-1, len(COLUMNS))
    except ValueError:
        raise TrajectoryError('%s: rows must hold %d numbers each' % (path, len(COLUMNS))) from None
    return {name: table[:, i] for i, name in enumerate(COLUMNS)}
