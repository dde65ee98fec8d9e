"""A sweep's table and verdicts: the columns of runs.csv, the percentiles of
summary.json, and one run's parameter file written back for a rerun.

The metrics per run (``METRICS``) are described in ``sweep``, which computes
them.
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stewart63_ros.core.analysis.sweep_plan import SweepPlan, Variation, _file_faults, apply_values

METRICS = ('final_error_percent', 'max_force', 'settling_time_s', 'endstop_samples',
           'diverged')
#: The percentiles summary.json gives per column.
PERCENTILES = (0, 5, 25, 50, 75, 95, 100)



def columns(plan: SweepPlan) -> list[str]:
    """Columns of runs.csv: run, each varied key (``param.<key>``), each fault
    pattern's drawn parts (``fault<n>.<field>``) and fault (``fault<n>``), the
    metrics, failure. No two share a name.

    Args:
        plan: the sweep.

    Returns:
        The column names in order.
    """
    faults = []
    for pattern in plan.faults:
        faults += [a.column for a in pattern.axes] + [pattern.column]
    return (['run'] + [v.column for v in plan.variations] + faults + list(METRICS)
            + ['failure'])


def summary(plan: SweepPlan,
            rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Percentiles (0, 5, 25, 50, 75, 95, 100), mean and count of every numeric
    column over the runs that finished; ``diverged``: how many did not.

    Args:
        plan: the sweep.
        rows: the runs' rows (``run_sweep``'s 'rows').

    Returns:
        {axis column or metric: {'count': int (finite values), 'p0' ... 'p100',
        'mean' (when count > 0)}, 'diverged': {'count': int}}, in the column's
        unit.
    """
    done = [r for r in rows if not r['diverged']]
    out: dict[str, dict[str, float]] = {}
    for key in [a.column for a in plan.axes] + list(METRICS[:-1]):
        data = np.array([r[key] for r in done], dtype=float)
        data = data[np.isfinite(data)]
        stats: dict[str, float] = {'count': int(data.size)}
        if data.size:
            stats.update({'p%d' % p: float(v) for p, v in zip(PERCENTILES,
                                                              np.percentile(data, PERCENTILES))})
            stats['mean'] = float(data.mean())
        out[key] = stats
    out['diverged'] = {'count': int(sum(r['diverged'] for r in rows))}
    return out


def write_run_parameters(params_path: str | os.PathLike, out_path: str | os.PathLike,
                         variations: Iterable[Variation], values: Iterable[float],
                         faults: Iterable[str] = ()) -> None:
    """Write the parameter file of one run: ``params_path`` with each varied key
    set in every section that has it (in the wildcard section ``/**`` when
    none has it), and the run's ``--fault`` s (its ``fault<n>`` columns) added
    to the plant's ``faults``, so that ``sim --params out_path`` reproduces the
    run (``--control sampled`` for a sampled sweep without faults).

    Args:
        params_path: the sweep's ROS 2 parameter file (read).
        out_path: the run's parameter file (written, YAML).
        variations: the varied parameters; values: (K,) the run's values.
        faults: the run's resolved fault strings (``fault<n>`` of runs.csv).
    """
    doc = yaml.safe_load(Path(params_path).read_text())
    sections = [s['ros__parameters'] for s in doc.values()
                if isinstance(s, dict) and isinstance(s.get('ros__parameters'), dict)]
    wildcard = next((doc[k]['ros__parameters'] for k in doc if str(k).strip() in ('/**', '**')),
                    sections[0])
    for var, value in zip(variations, values):
        holders = [s for s in sections if var.name in s] or [wildcard]
        for section in holders:
            section.update(apply_values(section, [var], [value]))
    faults = list(faults)
    if faults:
        plant = next((doc[k]['ros__parameters'] for k in doc if str(k).split('/')[-1] == 'plant'
                      and isinstance(doc[k], dict)), wildcard)
        plant['faults'] = _file_faults(plant) + faults
    Path(out_path).write_text(yaml.safe_dump(doc, sort_keys=False))
