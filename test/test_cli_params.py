"""Every executable that takes ``--params`` names the file's unknown keys
(a warning, "did you mean"), as docs/interface.md promises: ``plot``,
``plot --animate`` and ``view`` as ``sim``, ``rig`` and ``fk --solve`` do.
In-process, fast: each call stops at an error after reading the file."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stewart63_ros.core.plumbing.trajectory import COLUMNS, write_csv

REPO = Path(__file__).resolve().parents[1]
HINT = 'sensor_rat: unknown parameter (did you mean sensor_rate?)'


def params_with_a_typo(tmp_path) -> Path:
    text = (REPO / 'config' / 'stewart63.yaml').read_text()
    path = tmp_path / 'typo.yaml'
    path.write_text(text.replace('    platform_mass: 15.0',
                                 '    platform_mass: 15.0\n    sensor_rat: 500.0', 1))
    assert 'sensor_rat' in path.read_text()
    return path


def test_plot_names_unknown_keys(tmp_path, capsys):
    from stewart63_ros.tools import plot
    csv = tmp_path / 'trajectory.csv'
    write_csv(csv, np.zeros((3, len(COLUMNS))) + np.arange(3)[:, None])
    assert plot.main([str(csv), '--params', str(params_with_a_typo(tmp_path)),
                      '--out', str(tmp_path / 'figure.png')]) == 0
    assert HINT in capsys.readouterr().err


def test_plot_animate_names_unknown_keys(tmp_path, capsys):
    from stewart63_ros.tools import plot
    # stops at the source, a folder that is not a bag, after the parameter
    # file: one line, exit 2
    with pytest.raises(SystemExit) as exc:
        plot.main(['--animate', str(tmp_path), '--params', str(params_with_a_typo(tmp_path)),
                   '--out', str(tmp_path / 'a.gif')])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and HINT in err and 'not a bag' in err, err


def test_view_names_unknown_keys(tmp_path, capfd):
    from stewart63_ros.tools import view
    # stops at the BAG, which is not a bag, after the parameter file: exit 2
    code = view.main(['--params', str(params_with_a_typo(tmp_path)), str(tmp_path)])
    err = capfd.readouterr().err
    assert code == 2 and HINT in err, err
