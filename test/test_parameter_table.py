"""The node parameters are declared once (core/node_parameters.py): the
interface page's table, the known keys, the checks and the run-time changes
all follow the declarations.

``python test/test_parameter_table.py --write`` rewrites the page's table
from the declarations.
"""
from __future__ import annotations

import ast
import math
import sys
from pathlib import Path

import pytest

from stewart63_ros.core import node_parameters as declared
from stewart63_ros.core.errors import ParameterError
from stewart63_ros.core.params import default_params_path, file_parameters, known_keys

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / 'docs' / 'interface.md'
BEGIN = '<!-- generated from core/node_parameters.py'
END = '<!-- end of the generated table -->'


def page_table(text: str) -> tuple[int, int]:
    """Where the generated table sits in the page: (start, end) offsets."""
    start = text.index('\n', text.index(BEGIN)) + 1
    return start, text.index(END, start)


def expected_table() -> str:
    return declared.markdown_table(file_parameters(default_params_path()))


def test_the_interface_page_shows_the_declared_table():
    text = DOC.read_text()
    start, end = page_table(text)
    assert text[start:end] == expected_table(), (
        'docs/interface.md differs from core/node_parameters.py: run '
        'python test/test_parameter_table.py --write')


def test_every_declared_key_is_known_and_its_default_passes_its_check():
    for d in declared.DECLARED:
        assert d.name in known_keys()
        assert d.nodes and set(d.nodes) <= {*declared.NODES, 'sim'}, d.name
        assert d.doc and d.check, d.name
        declared.read({}, d.name)                   # raises if the default is refused
    assert len(declared.BY_NAME) == len(declared.DECLARED), 'a key declared twice'


@pytest.mark.parametrize('name, bad', [
    ('sensor_rate', 0), ('sensor_rate', math.inf), ('sensor_rate', 'fast'),
    ('clock_mode', 'bogus'), ('duration', -1.0), ('lockstep_window', 901),
    ('lockstep_window', 2.5), ('lockstep_window', True), ('lengths_peers', 'fk'),
    ('sensor_noise', math.nan), ('endstop_stiffness', -1.0), ('marker_rate', 201),
    ('realtime_priority', 100), ('strict_parameters', 'yes'), ('ct_kp', [1.0] * 5),
    ('faults', ['sensor_stuck:leg_0']), ('step_count', 0), ('control_law', 3),
    ('summary_file', 5)])
def test_a_value_out_of_its_declared_range_is_refused_naming_its_key(name, bad):
    with pytest.raises(ParameterError) as info:
        declared.read({name: bad}, name)
    assert str(info.value).startswith(name + ': ')


def test_read_gives_the_default_the_given_value_and_a_dependent_default():
    assert declared.read({}, 'sensor_rate') == 1000.0
    assert declared.read({'sensor_rate': 250}, 'sensor_rate') == 250.0
    assert declared.read({'lockstep_window': 20.0}, 'lockstep_window') == 20
    assert declared.read({}, 'watchdog_timeout') == 0.1
    assert declared.read({'clock_mode': 'lockstep'}, 'watchdog_timeout') == 2.0
    assert declared.read({'reference_file': None}, 'reference_file') == ''


def _tunable_keys() -> set[str]:
    """The keys the nodes let change at run time: ``self.tunable('x', ...)``
    calls, and the controller's ``for name in LAW_PARAMETERS`` loop."""
    from stewart63_ros.core.laws import LAW_PARAMETERS
    keys = set()
    for path in (REPO / 'stewart63_ros' / 'nodes').glob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == 'tunable' and node.args:
                arg = node.args[0]
                if isinstance(arg, ast.Constant):
                    keys.add(arg.value)
                elif isinstance(arg, ast.Name) and arg.id == 'name':
                    keys |= set(LAW_PARAMETERS)
    return keys


def test_the_keys_declared_changeable_at_run_time_are_the_ones_the_nodes_let_change():
    runtime = {d.name for d in declared.DECLARED if d.runtime}
    tunable = _tunable_keys() & set(declared.BY_NAME)     # kp, kv are the model's
    assert tunable == runtime
    assert {'control_law', 'ct_kp', 'faults'} <= runtime


def test_the_model_table_lists_exactly_the_mechanisms_keys():
    """The model's keys are declared by ``params.Mechanism`` (checked together
    by ``mechanism_from_params``); the page's model table has one row each."""
    import dataclasses
    import re

    from stewart63_ros.core.params import Mechanism
    text = DOC.read_text()
    section = text[text.index('### The model (shared keys)'):text.index('### Node-specific keys')]
    rows = re.findall(r'^\| `([a-z_]+)` \|', section, re.M)
    assert sorted(rows) == sorted(f.name for f in dataclasses.fields(Mechanism)
                                  if f.name != 'extra')
    assert len(rows) == len(set(rows))


if __name__ == '__main__':
    if sys.argv[1:] != ['--write']:
        sys.exit('usage: python test/test_parameter_table.py --write')
    text = DOC.read_text()
    start, end = page_table(text)
    DOC.write_text(text[:start] + expected_table() + text[end:])
    print('docs/interface.md: the table of node-specific keys rewritten')
