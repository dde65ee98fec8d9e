"""The core's public API is documented and typed: every public function and
method of stewart63_ros/core has a docstring and full type hints (every
parameter and the return), so that the next engineer reads shapes and units
where the function is (Args/Returns, as NumPy's and MuJoCo's bindings do).

Public: a module-level function or a method of a public class whose name does
not start with ``_``, and ``__init__`` (its Args live in the class docstring,
so the class needs one) and ``__call__`` of a public class. Functions nested
in functions (closures) and private classes are not API.

Numba kernels (``@njit``, ``@njit_kernel``) are held to the same rule: their
annotations are strings under ``from __future__ import annotations`` that
numba never reads (it types a kernel from the arguments of each call), and
every public kernel has them already. ``precompile.main`` is the entry point
of ``python -m stewart63_ros.core.precompile`` (no arguments) and is typed
too, so nothing is exempt.

A static scan (ast): nothing is imported, no kernel is compiled.
"""
from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / 'stewart63_ros' / 'core'
FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)
PUBLIC_DUNDERS = ('__init__', '__call__')


def _is_public(name: str) -> bool:
    return not name.startswith('_') or name in PUBLIC_DUNDERS


def _public_functions(tree: ast.Module):
    """(qualified name, function node, its class node or None) of every public
    function of a module: module level, and methods of public classes (nested
    classes included)."""
    def visit(body, prefix, cls):
        for node in body:
            if isinstance(node, ast.ClassDef) and not node.name.startswith('_'):
                yield from visit(node.body, prefix + node.name + '.', node)
            elif isinstance(node, FUNCTIONS) and (
                    not node.name.startswith('_') or cls is not None and _is_public(node.name)):
                yield prefix + node.name, node, cls
    yield from visit(tree.body, '', None)


def _unannotated(func: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> list[str]:
    """The parameters without an annotation (``self``/``cls`` of a method aside),
    and 'return' when the return is not annotated."""
    args = func.args
    params = args.posonlyargs + args.args
    if method and params and not any(isinstance(d, ast.Name) and d.id == 'staticmethod'
                                     for d in func.decorator_list):
        params = params[1:]          # self, or cls of a classmethod
    params = params + args.kwonlyargs + [a for a in (args.vararg, args.kwarg) if a]
    missing = [a.arg for a in params if a.annotation is None]
    if func.returns is None:
        missing.append('return')
    return missing


def problems(source: str, module: str) -> list[str]:
    """One line per public function of ``source`` without a docstring or with
    a missing type hint."""
    out = []
    for name, func, cls in _public_functions(ast.parse(source)):
        where = '%s:%d %s' % (module, func.lineno, name)
        if func.name == '__init__':
            if not ast.get_docstring(cls):
                out.append('%s: no class docstring (the Args of __init__)' % where)
        elif not ast.get_docstring(func):
            out.append('%s: no docstring' % where)
        missing = _unannotated(func, cls is not None)
        if missing:
            out.append('%s: no type hint for %s' % (where, ', '.join(missing)))
    return out


def core_modules() -> list[Path]:
    return sorted(CORE.rglob('*.py'))


def test_the_scan_finds_what_it_looks_for():
    source = '''
def good(x: int) -> int:
    """Doc."""
def no_doc(x: int) -> int:
    pass
def no_hints(x, *args: int, y, **kw) -> None:
    """Doc."""
def no_return(x: int):
    """Doc."""
def _private(x):
    pass
def outer() -> None:
    """Doc."""
    def closure(x):
        pass
class Public:
    """Doc."""
    def __init__(self, a) -> None:
        pass
    def __call__(self, x: float) -> float:
        pass
    @staticmethod
    def static(x) -> None:
        """Doc."""
    @property
    def prop(self) -> int:
        """Doc."""
    def __repr__(self):
        pass
    class Inner:
        def method(self):
            pass
class _Private:
    def method(self, x):
        pass
class NoDoc:
    def __init__(self) -> None:
        pass
'''
    assert problems(source, 'm.py') == [
        'm.py:4 no_doc: no docstring',
        'm.py:6 no_hints: no type hint for x, y, kw',
        'm.py:8 no_return: no type hint for return',
        'm.py:18 Public.__init__: no type hint for a',
        'm.py:20 Public.__call__: no docstring',
        'm.py:23 Public.static: no type hint for x',
        'm.py:31 Public.Inner.method: no docstring',
        'm.py:31 Public.Inner.method: no type hint for return',
        'm.py:37 NoDoc.__init__: no class docstring (the Args of __init__)',
    ]


def test_the_scan_sees_the_core():
    names = {name for path in core_modules()
             for name, _, _ in _public_functions(ast.parse(path.read_text()))}
    # a plain function, a method, a property, a numba kernel, __init__, __call__
    assert {'leg_lengths', 'Dynamics.derivative', 'Equilibrium.theta', 'pd_law',
            'PDController.__init__', 'Controller.__call__', 'main'} <= names
    assert len(names) > 200


def test_every_public_function_of_the_core_has_a_docstring_and_type_hints():
    found = [line for path in core_modules()
             for line in problems(path.read_text(), path.name)]
    assert found == [], 'public API of stewart63_ros/core without a docstring or ' \
        'type hints:\n' + '\n'.join(found)
