"""docs/interface.md keeps up with the code.

Every parameter a node, the sensor model, the dynamics or ``sim`` reads, every
topic name in ``stewart63_ros/topics.py``, every console script in setup.py,
every command-line option, every rejection reason and every diagnostics key
must appear on the interface page (in backticks). The names are found by
reading the source (no import, no ROS), so a parameter or an option added
without documenting it fails here, with its name and where it is read.
"""
from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / 'stewart63_ros'
DOC = ROOT / 'docs' / 'interface.md'
#: Parameters that belong to rclpy, not to us.
ROS_OWN = {'use_sim_time'}


@functools.lru_cache(maxsize=1)
def _sources() -> tuple:
    """(path, syntax tree) of every module of the package, parsed once."""
    return tuple((path, ast.parse(path.read_text(), filename=str(path)))
                 for path in sorted(PACKAGE.rglob('*.py')))


def _const_str(node):
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


def _tail_name(node):
    """``params`` for ``params``, ``self.params`` and ``mech.extra`` -> ``extra``."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _rignode_accessors() -> set[str]:
    """RigNode methods taking a parameter name first (``param``, ``positive``, ...)."""
    tree = ast.parse((PACKAGE / 'runtime' / 'base.py').read_text())
    found = set()
    for cls in ast.walk(tree):
        if isinstance(cls, ast.ClassDef) and cls.name == 'RigNode':
            for fn in cls.body:
                if isinstance(fn, ast.FunctionDef) and len(fn.args.args) > 1 \
                        and fn.args.args[1].arg == 'name' and not fn.name.startswith('_'):
                    found.add(fn.name)
    return found


def parameters_read() -> dict[str, str]:
    """{parameter: 'file:line' of one place that reads it}."""
    accessors = _rignode_accessors()
    found = {}

    def add(key, path, node):
        if key and key not in ROS_OWN and re.fullmatch(r'[a-z][a-z0-9_]*', key):
            found.setdefault(key, '%s:%d' % (path.relative_to(ROOT), node.lineno))

    for path, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and node.args:
                func = node.func
                first = _const_str(node.args[0])
                # self.param('x'), self.peer_names('x'), self.tunable('x', ...)
                if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) \
                        and func.value.id == 'self' and func.attr in accessors:
                    add(first, path, node)
                # params.get('x'), self.params.get('x'), mech.extra.get('x')
                elif isinstance(func, ast.Attribute) and func.attr == 'get' \
                        and _tail_name(func.value) in ('params', 'extra'):
                    add(first, path, node)
                # _scalar(params, 'x'), read_declared(mech.extra, 'x')
                elif _tail_name(node.args[0]) in ('params', 'extra') and len(node.args) > 1:
                    add(_const_str(node.args[1]), path, node)
            # params['x']
            elif isinstance(node, ast.Subscript) and _tail_name(node.value) in ('params', 'extra'):
                add(_const_str(node.slice), path, node)
            # the fields of the Mechanism dataclass
            elif isinstance(node, ast.ClassDef) and node.name == 'Mechanism':
                for item in node.body:
                    if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name) \
                            and item.target.id != 'extra':
                        add(item.target.id, path, item)
    return found


def topic_names() -> dict[str, str]:
    """{topic name: constant} for every module-level string constant in topics.py."""
    tree = ast.parse((PACKAGE / 'topics.py').read_text())
    found = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and _const_str(node.value):
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id.isupper():
                    found[node.value.value] = target.id
    return found


def console_scripts() -> list[str]:
    text = (ROOT / 'setup.py').read_text()
    text = text[text.index("'console_scripts'"):]       # not the can.interface entry point
    text = text[:text.index(']')]
    return re.findall(r"'([\w-]+)\s*=\s*stewart63_ros\.[\w.]+:\w+'", text)


def command_options() -> dict[str, str]:
    """{'--option': 'file:line'} for every add_argument in the package."""
    found = {}
    for path, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == 'add_argument':
                for arg in node.args:
                    name = _const_str(arg)
                    if name and name.startswith('-'):
                        found.setdefault(name, '%s:%d' % (path.relative_to(ROOT), node.lineno))
    return found


def rejection_reasons() -> dict[str, str]:
    found = {}
    for path, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and _tail_name(node.func) == 'Rejected' and node.args:
                reason = _const_str(node.args[0])
                if reason:
                    found.setdefault(reason, '%s:%d' % (path.relative_to(ROOT), node.lineno))
    return found


def diagnostics_keys() -> dict[str, str]:
    """Keys a node puts into its /diagnostics values, and the fixed key prefixes."""
    found = {}

    def add(key, path, node):
        if key:
            found.setdefault(key, '%s:%d' % (path.relative_to(ROOT), node.lineno))

    for path, tree in _sources():
        for node in ast.walk(tree):
            # health.values.update(a=..., b=...) or .update({'a': ...})
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == 'update' and _tail_name(node.func.value) == 'values':
                for kw in node.keywords:
                    add(kw.arg, path, node)
                for arg in node.args:
                    if isinstance(arg, ast.Dict):
                        for key in arg.keys:
                            add(_const_str(key), path, node)
            # health.values['a'] = ...
            elif isinstance(node, ast.Assign):
                for target in node.targets:
                    if isinstance(target, ast.Subscript) \
                            and isinstance(target.value, ast.Attribute) \
                            and target.value.attr == 'values':
                        add(_const_str(target.slice), path, node)
            # KeyValue(key='received/' + topic) / KeyValue(key='rejected_total', ...)
            elif isinstance(node, ast.Call) and _tail_name(node.func) == 'KeyValue':
                for kw in node.keywords:
                    if kw.arg == 'key':
                        value = kw.value
                        if isinstance(value, ast.BinOp):
                            value = value.left
                        add(_const_str(value), path, node)
    return found


def code_spans(text: str) -> list[str]:
    """Everything between backticks, and every indented code line."""
    spans = re.findall(r'`([^`]+)`', text)   # Markdown pairs backticks in order
    spans += [line.strip() for line in text.splitlines() if line.startswith('    ')]
    return spans


def documented(name: str, spans: list[str], prefix: bool = False) -> bool:
    """``name`` is a whole word of some code span (or starts one, for key prefixes)."""
    pattern = re.compile(r'(?<![\w/-])' + re.escape(name) + ('' if prefix else r'(?![\w-])'))
    return any(pattern.search(span) for span in spans)


def missing(found: dict, spans: list[str], prefix_ok=False) -> list[str]:
    return ['%s (%s)' % (name, where) for name, where in sorted(found.items())
            if not documented(name, spans, prefix=prefix_ok and name.endswith('/'))]


@pytest.fixture(scope='module')
def spans():
    return code_spans(DOC.read_text())


def test_the_scanners_find_what_the_code_reads():
    # A scanner that finds nothing would let every check below pass.
    params = parameters_read()
    for key in ('base_points', 'kp', 'initial_orientation_rate', 'sensor_rate', 'clock_mode',
                'sensor_noise', 'endstop_stiffness', 'watchdog_timeout',
                'singularity_threshold', 'realtime_priority', 'discovery_timeout'):
        assert key in params, key
    assert {'leg_lengths', 'ground_truth/pose', '/clock', '/diagnostics'} <= set(topic_names())
    assert {'plant', 'controller', 'fk', 'record', 'play', 'rig', 'sim', 'plot'} \
        <= set(console_scripts())
    assert {'--record', '--mode', '--recover', '--wait-subscribers', '--solve'} \
        <= set(command_options())
    assert {'non_finite', 'stamp_from_past', 'no_assembly'} <= set(rejection_reasons())
    assert {'endstop_samples', 'setpoint', 'singular_samples', 'received/',
            'rejected_total'} <= set(diagnostics_keys())


def test_the_check_fails_on_an_undocumented_name():
    spans = code_spans('`sensor_rate` and `--record DIR`, `received/<topic>`')
    assert missing({'sensor_rate': 'x'}, spans) == []
    assert missing({'sensor_rat': 'x'}, spans) == ['sensor_rat (x)']
    assert missing({'sensor_rate_noise': 'x'}, spans) == ['sensor_rate_noise (x)']
    assert missing({'--record': 'x', '--rec': 'y'}, spans) == ['--rec (y)']
    assert missing({'received/': 'x'}, spans, prefix_ok=True) == []


def test_every_parameter_is_documented(spans):
    assert missing(parameters_read(), spans) == [], \
        'parameters read by the code but not in docs/interface.md'


def test_every_topic_is_documented(spans):
    assert missing({name: 'topics.' + const for name, const in topic_names().items()},
                   spans) == [], 'topics not in docs/interface.md'


def test_every_executable_is_documented(setup, spans):
    assert missing({name: 'setup.py' for name in console_scripts()}, spans) == [], \
        'console scripts not in docs/interface.md'


def test_every_command_line_option_is_documented(spans):
    assert missing(command_options(), spans) == [], 'options not in docs/interface.md'


def test_every_rejection_reason_is_documented(spans):
    assert missing(rejection_reasons(), spans) == [], \
        'rejection reasons not in docs/interface.md'


def test_every_diagnostics_key_is_documented(spans):
    assert missing(diagnostics_keys(), spans, prefix_ok=True) == [], \
        'diagnostics keys not in docs/interface.md'


def test_no_reference_to_documents_a_user_does_not_have(setup):
    # Built so that this file does not match itself.
    pattern = re.compile('|'.join(['CONTR' + 'ACT', 'FA' + 'CTS', r'[Ii]ssue\s+#?[0-9]']))
    places = [ROOT / 'README.md', ROOT / 'Makefile', ROOT / 'setup.py', ROOT / 'package.xml']
    for folder in ('stewart63_ros', 'docs', 'launch', 'bench', 'test', 'config'):
        places += [p for p in (ROOT / folder).rglob('*')
                   if p.is_file() and p.suffix in ('.py', '.md', '.yaml', '.rviz', '.txt', '')
                   and '__pycache__' not in p.parts]
    hits = []
    for path in places:
        for number, line in enumerate(path.read_text(errors='replace').splitlines(), 1):
            if pattern.search(line):
                hits.append('%s:%d: %s' % (path.relative_to(ROOT), number, line.strip()))
    assert hits == [], '\n'.join(hits)


def test_the_tables_of_executables_list_every_console_script():
    """README's "What is in the box" and the interface's "Executables": one
    row per executable a user can run, no more, no fewer."""
    scripts = sorted(console_scripts())
    for path, heading in ((ROOT / 'README.md', '## What is in the box'),
                          (DOC, '### Executables')):
        text = path.read_text()
        section = text[text.index(heading):]
        section = section[:section.index('\n\n', section.index('|'))]
        rows = re.findall(r'^\| `([\w-]+)` \|', section, re.M)
        assert sorted(rows) == scripts, (path.name, sorted(set(scripts) ^ set(rows)))


def test_the_rig_table_lists_every_rig_option():
    """The `rig` table of the interface: one row per option of `rig`'s parser
    (`--supervisor` was missing)."""
    tree = ast.parse((ROOT / 'stewart63_ros' / 'tools' / 'rig.py').read_text())
    options = {_const_str(arg) for node in ast.walk(tree) if isinstance(node, ast.Call)
               and isinstance(node.func, ast.Attribute) and node.func.attr == 'add_argument'
               for arg in node.args if (_const_str(arg) or '').startswith('--')}
    text = DOC.read_text()
    section = text[text.index('**`rig [options]`**'):]
    section = section[:section.index('\n\n', section.index('|'))]
    rows = set(re.findall(r'^\| `(--[\w-]+)', section, re.M))
    assert '--supervisor' in options and options <= rows, sorted(options - rows)
