"""The package's import graph: every module imports, no two modules of
stewart63_ros import each other, directly or through others (function-level
and type-hint imports included: a cycle hidden in a function or behind
``if TYPE_CHECKING:`` is still a cycle), and no module imports up a floor.

The floors (docs/design.md), lowest first; a module imports only from its
own floor or those below:

1. the core (``stewart63_ros.core``, no ROS) and the package's ROS-free
   modules beside it (paths, topics, exits, bagio, bagruns, bagrepair, middleware,
   mujoco_model).
   Inside the core, floors by domain package (``CORE_FLOORS``), lowest first:
   ``plumbing`` (names, errors, the declaration of every key), ``mechanics``
   (the mechanism, kinematics, fk, dynamics), ``controllers`` (eq. (40), the
   laws, references, the sensor model, the offline closed loop), then
   ``machine`` (supervisor, bus, calibration, faults) and ``analysis``
   (equilibrium, linear model, modes, workspace, sweep) side by side,
   ``scenarios`` on top, and ``precompile`` (which calls every kernel) above
   all. A module of floor 0 imports nothing of the package but floor 0.
   A few modules sit on another floor than their package's, each with its
   reason (``CORE_FLOORS``).
2. the runtime (``stewart63_ros.runtime``): the rclpy machinery under the
   nodes; it imports neither the recorder nor a node.
3. recording (``stewart63_ros.recording``): the recorder, on the runtime; it
   imports no node.
4. the nodes (``stewart63_ros.nodes``): plant, controller, fk, composed (which
   runs the recorder in its process, hence above recording).
5. the tools, the examples and the pytest plugin (``stewart63_ros.tools``,
   ``stewart63_ros.examples``, ``stewart63_ros.pytest_plugin``).
"""
from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'stewart63_ros'


def modules() -> dict[str, Path]:
    """Every module of the package, by its dotted name."""
    out = {}
    for path in sorted(PACKAGE.rglob('*.py')):
        parts = list(path.relative_to(REPO).with_suffix('').parts)
        if parts[-1] == '__init__':
            parts.pop()
        out['.'.join(parts)] = path
    return out


#: The core's floors, by domain package (docs/design.md), lowest first. Same
#: floor: may import each other (no cycle: test_no_import_cycle_in_the_package).
#: A dotted module under the core names a module that sits on another floor
#: than its package, with the reason.
CORE_FLOORS = {
    'plumbing': 0,
    'mechanics': 1,
    'controllers': 2,
    'machine': 3,
    'analysis': 3,
    'scenarios': 4,
    # compiles every kernel: it imports them all
    'precompile': 5,
    # eq. (40), written once: mechanics.dynamics evaluates it inside the ODE
    'controllers.control': 0,
    # node_parameters checks the `faults` parameter with its parser
    'machine.faults': 0,
    # loading a file checks `control_law` against controllers.laws
    'plumbing.params': 2,
}
#: Before the core is in packages (a branch from before the move): its leaf modules.
CORE = 'stewart63_ros.core'
FLOOR_NAMES = ('', 'core', 'runtime', 'recording', 'nodes', 'tools')


def core_floor(name: str) -> int | None:
    """The floor of core module ``name`` inside the core (None: not in the
    core, or a core module the table does not place)."""
    if name == CORE or not name.startswith(CORE + '.'):
        return None
    parts = name[len(CORE) + 1:].split('.')
    for size in (2, 1):
        key = '.'.join(parts[:size])
        if len(parts) >= size and key in CORE_FLOORS:
            return CORE_FLOORS[key]
    return None


def floor(name: str) -> int:
    """The floor of module ``name`` (1 lowest; module docstring)."""
    if name.startswith(('stewart63_ros.tools', 'stewart63_ros.examples',
                        'stewart63_ros.pytest_plugin')):
        return 5
    for number, package in ((4, 'nodes'), (3, 'recording'), (2, 'runtime')):
        if name == 'stewart63_ros.' + package or name.startswith('stewart63_ros.%s.' % package):
            return number
    return 1


def label(name: str) -> str:
    """Where ``name`` sits, for a message: 'runtime', 'core/mechanics, floor 1'."""
    inside = core_floor(name)
    if inside is None:
        return FLOOR_NAMES[floor(name)] if floor(name) > 1 else (
            'core, no floor' if name.startswith(CORE + '.') else 'beside the core')
    parts = name[len(CORE) + 1:].split('.')
    where = 'core/' + parts[0] if len(parts) > 1 else 'core'
    return '%s, floor %d' % (where, inside)


def is_up(importer: str, imported_name: str) -> bool:
    """True when ``importer`` may not import ``imported_name`` (a higher floor)."""
    if floor(imported_name) != floor(importer):
        return floor(imported_name) > floor(importer)
    mine, theirs = core_floor(importer), core_floor(imported_name)
    if mine is not None and theirs is not None:
        return theirs > mine
    # The core's ground floor imports nothing of the package but the ground floor.
    return mine == 0 and theirs is None


def imported(path: Path, name: str, known: dict[str, Path]) -> set[str]:
    """The package's modules that ``path`` (module ``name``) imports, anywhere in
    it: at module level, in functions and under ``if TYPE_CHECKING:``."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parent = package.split('.')
                parent = parent[:len(parent) - node.level + 1]
                base = '.'.join(parent + ([base] if base else []))
            # `from pkg import mod` imports the module pkg.mod; `from mod import f` mod.
            targets = [base + '.' + alias.name if base + '.' + alias.name in known else base
                       for alias in node.names]
        else:
            continue
        out |= {t for t in targets if t in known and t != name}
    return out


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imported(path, name, known) for name, path in known.items()}


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_the_graph_sees_function_level_and_type_hint_imports(tmp_path):
    edges = graph()
    params = edges['stewart63_ros.core.plumbing.params']
    assert 'stewart63_ros.core.controllers.laws' in params     # in a function
    assert 'stewart63_ros.core.plumbing.errors' in params
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    hinted = tmp_path / 'm.py'
    hinted.write_text('from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n'
                      '    from stewart63_ros.core.plumbing.params import Mechanism\n')
    assert imported(hinted, 'stewart63_ros.core.m', modules()) == {
        'stewart63_ros.core.plumbing.params'}


def test_no_import_cycle_in_the_package():
    found = cycles(graph())
    assert found == [], 'modules that import each other: %s' % found


def up_a_floor(edges: dict[str, set[str]]) -> list[str]:
    """Every import of a module on a higher floor than the importer's."""
    return ['%s (%s) imports %s (%s)' % (a, label(a), b, label(b))
            for a in sorted(edges) for b in sorted(edges[a]) if is_up(a, b)]


def test_the_floor_rule_sees_an_import_up_a_floor():
    assert up_a_floor({'stewart63_ros.core.controllers.laws': {'stewart63_ros.runtime.wire'}}) == [
        'stewart63_ros.core.controllers.laws (%s) imports stewart63_ros.runtime.wire (runtime)'
        % label('stewart63_ros.core.controllers.laws')]
    assert up_a_floor({'stewart63_ros.runtime.base': {'stewart63_ros.nodes.plant',
                                                      'stewart63_ros.recording.recorder'}}) == [
        'stewart63_ros.runtime.base (runtime) imports stewart63_ros.nodes.plant (nodes)',
        'stewart63_ros.runtime.base (runtime) imports stewart63_ros.recording.recorder'
        ' (recording)']
    assert up_a_floor({'stewart63_ros.recording.recorder': {'stewart63_ros.nodes.composed',
                                                            'stewart63_ros.runtime.wire'}}) == [
        'stewart63_ros.recording.recorder (recording) imports stewart63_ros.nodes.composed'
        ' (nodes)']
    assert up_a_floor({'stewart63_ros.nodes.composed': {'stewart63_ros.recording.recorder',
                                                        'stewart63_ros.tools.rig'}}) == [
        'stewart63_ros.nodes.composed (nodes) imports stewart63_ros.tools.rig (tools)']
    assert up_a_floor({'stewart63_ros.core.mechanics.mechanism': {
        'stewart63_ros.core.plumbing.params'}}) != []
    assert up_a_floor({'stewart63_ros.tools.rig': {'stewart63_ros.runtime.wire',
                                                   'stewart63_ros.core.plumbing.legs'}}) == []
    # The domain packages' floors, whatever the tree (names of the packaged core).
    assert up_a_floor({'stewart63_ros.core.mechanics.dynamics': {
        'stewart63_ros.core.controllers.laws', 'stewart63_ros.core.controllers.control',
        'stewart63_ros.core.plumbing.errors'}}) == [
        'stewart63_ros.core.mechanics.dynamics (core/mechanics, floor 1) imports'
        ' stewart63_ros.core.controllers.laws (core/controllers, floor 2)']
    assert up_a_floor({'stewart63_ros.core.machine.supervisor': {
        'stewart63_ros.core.analysis.sweep', 'stewart63_ros.core.scenarios.scenario'}}) == [
        'stewart63_ros.core.machine.supervisor (core/machine, floor 3) imports'
        ' stewart63_ros.core.scenarios.scenario (core/scenarios, floor 4)']
    assert up_a_floor({'stewart63_ros.core.plumbing.node_parameters': {
        'stewart63_ros.core.machine.faults', 'stewart63_ros.paths'}}) == [
        'stewart63_ros.core.plumbing.node_parameters (core/plumbing, floor 0) imports'
        ' stewart63_ros.paths (beside the core)']
    assert up_a_floor({'stewart63_ros.core.machine.faults': {
        'stewart63_ros.core.mechanics.kinematics'}}) != []


def test_no_module_imports_up_a_floor():
    found = up_a_floor(graph())
    assert found == [], 'imports up a floor (module docstring):\n' + '\n'.join(found)


def test_every_core_module_has_a_floor():
    """Each module of the core is in a package of the floor table (or is one the
    table names), and every package and module the table names exists."""
    known = modules()
    unplaced = sorted(name for name in known
                      if name.startswith(CORE + '.') and core_floor(name) is None)
    assert unplaced == [], 'put these in a package of CORE_FLOORS: %s' % unplaced
    missing = sorted(key for key in CORE_FLOORS if '%s.%s' % (CORE, key) not in known)
    assert missing == [], 'CORE_FLOORS names what is not there: %s' % missing


@pytest.mark.parametrize('name', sorted(modules()))
def test_every_module_imports(name):
    if name.endswith('__main__'):
        pytest.skip('runs a program')
    try:
        importlib.import_module(name)
    except ImportError as exc:
        # Optional dependencies: MuJoCo (the bench extra), tf2_msgs (a ROS install).
        if exc.name in ('mujoco', 'tf2_msgs'):
            pytest.skip('optional dependency %s' % exc.name)
        raise


def test_rotations_go_through_core_rotation():
    """One place for the orientation convention: scipy's Rotation (and its
    Euler angles), and the hand-written quaternion <-> matrix conversions of
    the compiled paths, only in core/mechanics/rotation.py."""
    offenders = []
    for name, path in modules().items():
        if name == 'stewart63_ros.core.mechanics.rotation':
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if any(word in line for word in ('scipy.spatial.transform', '.from_euler(',
                                             '.as_euler(', 'Rotation.', '1 - 2 * (',
                                             '1.0 - 2.0 * (', 'sqrt(1.0 + tr')):
                offenders.append('%s:%d' % (path.relative_to(REPO), number))
    assert offenders == [], offenders


def test_package_xml_lists_every_ros_package_imported():
    """A ROS install (rosdep, colcon) learns the runtime dependencies from
    package.xml: every ROS package the code imports is an exec_depend there."""
    declared = set(re.findall(r'<exec_depend>([\w-]+)</exec_depend>',
                              (REPO / 'package.xml').read_text()))
    used = set()
    for path in modules().values():
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.module
                     and not node.level else [])
            for name in names:
                top = name.split('.')[0]
                if top == 'rclpy' or top.endswith(('_msgs', '_interfaces')):
                    used.add(top)
    assert used - declared == set(), 'add to package.xml: %s' % sorted(used - declared)


def test_one_list_of_the_rigs_nodes():
    """rig, composed and the parameter declarations name the same nodes: the
    leaf node_names holds the list (rig imports it before its stop handlers)."""
    from stewart63_ros.core.plumbing import node_names, node_parameters
    from stewart63_ros.nodes import composed
    from stewart63_ros.tools import rig
    assert rig.NODES is composed.NODE_NAMES is node_names.NODES
    assert tuple(node_parameters.NODES) == node_names.ALL_NODES



#: The mark of an import left inside a function on purpose, with its measured
#: cost: ``# lazy: matplotlib costs 1450 ms at start-up; only --plot draws``.
LAZY_MARK = '# lazy:'
#: A figure the reason must carry: a measured cost in ms (docs/design.md, the
#: table), or the words "cycle" or "floor" for an import that would close a
#: circle or go up a floor, or "optional" for a dependency that may be absent.
LAZY_FIGURE = re.compile(r'\d+(\.\d+)?\s*ms\b|\b(cycle|floor|optional)\b')


def function_level_imports(source: str) -> list[tuple[int, str]]:
    """Every import inside a function of ``source`` without a lazy mark with a
    figure, as (line, problem). The mark sits on one of the import's lines or
    on the comment lines directly above a run of imports the import is in."""
    lines = source.splitlines()
    found = []

    def marked(start: int, end: int) -> str | None:
        for line in lines[start - 1:end]:
            if LAZY_MARK in line:
                return line
        return None

    def check_block(block: list[ast.stmt]) -> None:
        above = None          # the lazy comment over the current run of imports
        for stmt in block:
            if not isinstance(stmt, (ast.Import, ast.ImportFrom)):
                above = None
                continue
            comment = marked(stmt.lineno, stmt.end_lineno)
            if comment is None and above is None:
                # comment lines directly above this import
                row = stmt.lineno - 2
                while row >= 0 and lines[row].strip().startswith('#'):
                    if LAZY_MARK in lines[row]:
                        comment = lines[row]
                        break
                    row -= 1
            comment = comment or above
            if comment is None:
                found.append((stmt.lineno, 'no %r comment' % LAZY_MARK))
            elif not LAZY_FIGURE.search(comment.split(LAZY_MARK, 1)[1]):
                found.append((stmt.lineno, 'lazy comment without a cost in ms'))
            above = comment

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if inside:
                for field in ('body', 'orelse', 'finalbody'):
                    block = getattr(child, field, None)
                    if isinstance(block, list) and block and isinstance(block[0], ast.stmt):
                        check_block(block)
            walk(child, inside)

    walk(ast.parse(source), False)
    return sorted(set(found))


def test_the_lazy_rule_sees_an_unexplained_function_level_import():
    source = ('import os\n\n'
              'def f():\n    import json\n    return json\n\n'
              'def g():\n    import yaml  # lazy: yaml is slow\n\n'
              'def h():\n    # lazy: matplotlib costs 1450 ms at start-up; only --plot draws\n'
              '    import matplotlib\n    import matplotlib.pyplot as plt\n'
              '    plt.figure()\n    import scipy\n\n'
              'def k():\n    if True:\n        from a import b  # lazy: cycle (a imports us)\n'
              '    try:\n        import mujoco\n    except ImportError:\n        pass\n'
              '    try:\n        import tf2_msgs  # lazy: optional: a ROS install only\n'
              '    except ImportError:\n        pass\n'
              '    import yaml  # lazy: yaml costs 10ms; rig --help answers without it\n')
    assert function_level_imports(source) == [
        (4, "no '# lazy:' comment"), (8, 'lazy comment without a cost in ms'),
        (15, "no '# lazy:' comment"), (21, "no '# lazy:' comment")]


#: Directories whose modules' function-level imports are checked.
LAZY_CHECKED = (PACKAGE, REPO / 'bench')


def test_every_function_level_import_says_why_with_its_cost():
    """Imports sit at module level, where a reader sees the module's
    dependencies; one inside a function says why on a `# lazy:` line with the
    cost it saves at start-up (docs/design.md, the table of measured costs)."""
    offenders = []
    for directory in LAZY_CHECKED:
        for path in sorted(directory.rglob('*.py')):
            for line, problem in function_level_imports(path.read_text()):
                offenders.append('%s:%d: %s' % (path.relative_to(REPO), line, problem))
    assert offenders == [], '%d function-level imports without a reason:\n%s' % (
        len(offenders), '\n'.join(offenders))
