"""The node parameters are declared once (core/plumbing/node_parameters.py): the
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

from stewart63_ros.core.plumbing import node_parameters as declared
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.params import default_params_path, file_parameters, known_keys

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / 'docs' / 'interface.md'
BEGIN = '<!-- generated from core/plumbing/node_parameters.py'
MODEL_BEGIN = '<!-- generated from core/plumbing/node_parameters.py MODEL'
END = '<!-- end of the generated table -->'


def page_table(text: str, begin: str = BEGIN) -> tuple[int, int]:
    """Where a generated table sits in the page: (start, end) offsets (the
    node-specific keys' table is the last one)."""
    at = text.index(begin) if begin == MODEL_BEGIN else text.rindex(begin)
    start = text.index('\n', at) + 1
    return start, text.index(END, start)


def expected_table() -> str:
    return declared.markdown_table(file_parameters(default_params_path()))


def rewrite(text: str) -> str:
    """The page with both generated tables as the declarations give them."""
    for begin, table in ((MODEL_BEGIN, declared.model_markdown_table()),
                         (BEGIN, expected_table())):
        start, end = page_table(text, begin)
        text = text[:start] + table + text[end:]
    return text


def test_the_interface_page_shows_the_declared_table():
    text = DOC.read_text()
    start, end = page_table(text)
    assert text[start:end] == expected_table(), (
        'docs/interface.md differs from core/plumbing/node_parameters.py: run '
        'python test/test_parameter_table.py --write')


def test_the_interface_pages_model_table_is_the_declared_one():
    text = DOC.read_text()
    start, end = page_table(text, MODEL_BEGIN)
    assert text[start:end] == declared.model_markdown_table(), (
        'docs/interface.md differs from core/plumbing/node_parameters.py: run '
        'python test/test_parameter_table.py --write')


def test_the_model_declarations_are_the_mechanisms_fields():
    """``MODEL`` declares the machine's fields (but for the end stops and sensor
    zeros, declared with the nodes' keys), then the gains, then the task, in
    the order of their dataclasses (core/mechanics/setup.py)."""
    import dataclasses

    from stewart63_ros.core.mechanics.mechanism import Mechanism
    from stewart63_ros.core.mechanics.setup import Gains, Task
    machine = [f.name for f in dataclasses.fields(Mechanism) if f.name not in declared.BY_NAME]
    assert [m.name for m in declared.MODEL] == machine + [
        f.name for part in (Gains, Task) for f in dataclasses.fields(part)]
    params = dict(file_parameters(default_params_path()))
    for m in declared.MODEL:        # the size declared is the one the packaged file has
        value = params[m.name]
        assert (len(value) if isinstance(value, list) else 1) == m.size, m.name


def test_each_declaration_gives_what_ros2_param_describe_shows():
    """Every key of every node: a unit in the description where it has one,
    a range only on a number (rcl checks none on a list), read-only unless
    the node lets it change at run time, and a value of the declared ROS type."""
    for node in declared.NODES:
        for name in declared.node_keys(node):
            if name == 'use_sim_time':
                continue
            d = declared.describe(name, node)
            unit = (declared.MODEL_BY_NAME[name].unit if name in declared.MODEL_BY_NAME
                    else declared.BY_NAME[name].unit)
            assert not unit or d.description.endswith('[%s]' % unit), (node, name)
            assert '`' not in d.description + d.constraints and '](' not in d.description
            assert d.range is None or d.type in ('double', 'integer'), (node, name)
            assert d.range is None or d.range[0] <= d.range[1]
            runtime = (node in declared.MODEL_BY_NAME[name].runtime
                       if name in declared.MODEL_BY_NAME else declared.BY_NAME[name].runtime)
            assert d.read_only is not runtime, (node, name)
            if name in declared.BY_NAME:
                value = declared.ros_value(name, declared.default(name), node)
                check = declared.BY_NAME[name].check
                # the default passes the declared range as it passes the check
                check(name, value)
                if d.range is not None:
                    assert d.range[0] <= value <= d.range[1], (node, name, value)
    assert declared.describe('kp', 'plant').read_only
    assert not declared.describe('kp', 'controller').read_only
    assert declared.describe('sensor_rate', 'plant').range == (math.ulp(0.0), math.inf)
    assert declared.describe('lockstep_window', 'plant').range == (1, 900)
    assert declared.ros_value('sensor_rate', 1000, 'plant') == 1000.0
    assert declared.ros_value('faults', 'actuator_dead:leg_1', 'plant') == ['actuator_dead:leg_1']
    assert declared.ros_value('kp', [1, 2, 3, 4, 5, 6], 'fk') == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def test_every_declared_key_is_known_and_its_default_passes_its_check():
    from stewart63_ros.core.plumbing.node_names import ALL_NODES
    for d in declared.DECLARED:
        assert d.name in known_keys()
        assert d.nodes and set(d.nodes) <= {*ALL_NODES, 'sim'}, d.name
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
    from stewart63_ros.core.controllers.laws import LAW_PARAMETERS
    from stewart63_ros.core.machine.supervisor import LIMIT_KEYS
    keys = set()
    for path in [path for package in ('nodes', 'runtime', 'recording')
                 for path in (REPO / 'stewart63_ros' / package).glob('*.py')]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == 'tunable' and node.args:
                arg = node.args[0]
                if isinstance(arg, ast.Constant):
                    keys.add(arg.value)
                elif isinstance(arg, ast.Name) and arg.id == 'name':
                    keys |= set(LAW_PARAMETERS)
                elif isinstance(arg, ast.Name) and arg.id == 'limit_key':
                    keys |= set(LIMIT_KEYS)
    return keys


def test_the_keys_declared_changeable_at_run_time_are_the_ones_the_nodes_let_change():
    runtime = {d.name for d in declared.DECLARED if d.runtime}
    tunable = _tunable_keys() & set(declared.BY_NAME)     # kp, kv are the model's
    assert tunable == runtime
    assert {'control_law', 'ct_kp', 'faults'} <= runtime


def test_the_model_table_lists_exactly_the_mechanisms_keys():
    """The model's keys are the machine's (``Mechanism``, but for the end stops
    and sensor zeros declared with the nodes' keys), the gains and the task
    (core/mechanics/setup.py); the page's model table has one row each."""
    import re

    from stewart63_ros.core.mechanics.mechanism import MECHANISM_KEYS
    from stewart63_ros.core.mechanics.setup import GAIN_KEYS, TASK_KEYS
    text = DOC.read_text()
    section = text[text.index('### The model (shared keys)'):text.index('### Node-specific keys')]
    rows = re.findall(r'^\| `([a-z_]+)` \|', section, re.M)
    machine = MECHANISM_KEYS - set(declared.BY_NAME)
    assert sorted(rows) == sorted(machine | GAIN_KEYS | TASK_KEYS)
    assert len(rows) == len(set(rows))


def test_the_rigs_clock_mode_is_written_once_and_the_packaged_file_sets_it_for_every_node():
    """``rig``, ``demo`` and the launch files default to paths.RIG_CLOCK_MODE;
    the packaged file sets that mode in its ``/**`` section (every node reads
    it) and in no node's section; a node given none runs in the declared
    default."""
    import inspect

    import yaml

    from stewart63_ros.paths import RIG_CLOCK_MODE
    from stewart63_ros.tools.rig_process import Rig
    doc = yaml.safe_load(default_params_path().read_text())
    assert doc['/**']['ros__parameters']['clock_mode'] == RIG_CLOCK_MODE
    assert [k for k, v in doc.items() if k != '/**' and 'clock_mode' in v['ros__parameters']] \
        == []
    assert inspect.signature(Rig).parameters['mode'].default == RIG_CLOCK_MODE
    written = [path.name for path in [*(REPO / 'stewart63_ros').rglob('*.py'),
                                      *(REPO / 'launch').glob('*.py')]
               if "default='lockstep'" in path.read_text()
               or "default_value='lockstep'" in path.read_text()]
    assert written == []
    assert declared.default('clock_mode') == 'realtime'


if __name__ == '__main__':
    if sys.argv[1:] != ['--write']:
        sys.exit('usage: python test/test_parameter_table.py --write')
    DOC.write_text(rewrite(DOC.read_text()))
    print('docs/interface.md: the tables of the model\'s and the node-specific keys rewritten')
