"""One job a module, one job a class (docs/design.md, the layout).

- A module of the package over ``MODULE_LINES`` lines says why at its top:
  a line of its docstring begins ``Why this long:`` and gives the reason.
- No class is over ``CLASS_LINES`` lines (from its ``class`` line to its
  last), whatever its docstring says.

Today's exceptions are listed by name below, each with what is under way;
the list only shrinks: an entry whose module or class is back under the bar
(or has its reason written) fails too, so that it is struck off.

And docs/design.md's drawing of the core ("The core by domain") names every
module of every package, in its package, once the core is in packages.

A static scan (ast): nothing is imported.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'stewart63_ros'
MODULE_LINES = 600
CLASS_LINES = 350
WHY = 'Why this long:'

#: Modules over MODULE_LINES without a written reason, by path from the repository.
LONG_MODULES = {
}
#: Classes over CLASS_LINES, as 'path:Class'.
LONG_CLASSES = {
}


def long_modules(paths) -> list[str]:
    """Every module of ``paths`` over MODULE_LINES lines whose docstring has
    no line beginning with ``Why this long:``, as its path from the repository."""
    found = []
    for path in paths:
        source = path.read_text()
        if len(source.splitlines()) <= MODULE_LINES:
            continue
        doc = ast.get_docstring(ast.parse(source)) or ''
        if not any(line.strip().startswith(WHY) and line.strip() != WHY
                   for line in doc.splitlines()):
            found.append(path.relative_to(REPO).as_posix())
    return sorted(found)


def long_classes(paths) -> list[str]:
    """Every class of ``paths`` over CLASS_LINES lines, as 'path:Class'."""
    found = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > CLASS_LINES:
                found.append('%s:%s' % (path.relative_to(REPO).as_posix(), node.name))
    return sorted(found)


def package_modules() -> list[Path]:
    return sorted(PACKAGE.rglob('*.py'))


def test_the_scan_sees_a_long_module_and_a_long_class(tmp_path):
    body = '\n'.join('x%d = %d' % (i, i) for i in range(MODULE_LINES))
    cases = {
        'bare.py': '"""A module."""\n' + body,
        'reasoned.py': '"""A module.\n\nWhy this long: one table, generated.\n"""\n' + body,
        'empty_reason.py': '"""A module.\n\nWhy this long:\n"""\n' + body,
        'short.py': '"""A module."""\nx = 1\n',
        'big_class.py': 'class Big:\n' + '\n'.join('    a%d = %d' % (i, i)
                                                  for i in range(CLASS_LINES)) + '\n',
    }
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
    paths = sorted(tmp_path.glob('*.py'))
    global REPO
    saved, REPO = REPO, tmp_path
    try:
        assert long_modules(paths) == ['bare.py', 'empty_reason.py']
        assert long_classes(paths) == ['big_class.py:Big']
    finally:
        REPO = saved


def test_every_long_module_says_why():
    found = long_modules(package_modules())
    new = [path for path in found if path not in LONG_MODULES]
    assert new == [], ('modules over %d lines: split them by job, or write a line '
                       "'%s ...' in the module docstring:\n%s"
                       % (MODULE_LINES, WHY, '\n'.join(new)))


def test_no_class_over_the_bar():
    found = long_classes(package_modules())
    new = [name for name in found if name not in LONG_CLASSES]
    assert new == [], 'classes over %d lines: %s' % (CLASS_LINES, new)


def test_the_exceptions_only_shrink():
    """An exception that no longer applies (split, reasoned, moved) is struck off."""
    stale = sorted(set(LONG_MODULES) - set(long_modules(package_modules())))
    stale += sorted(set(LONG_CLASSES) - set(long_classes(package_modules())))
    assert stale == [], 'no longer over the bar (or moved): strike off %s' % stale


def drawn_core(text: str) -> set[str]:
    """'package/module.py' for every module the design page's drawing of the
    core places under a package (the fenced block after "The core by domain")."""
    block = text.split('### The core by domain', 1)[1].split('```', 2)[1]
    drawn, package = set(), None
    for line in block.splitlines():
        heading = re.match(r'^  (\w+)/', line)
        if heading:
            package = heading.group(1)
        elif package and line.startswith('    '):
            names = re.findall(r'^\s+((?:\w+\.py\s*)+)', line)
            for name in (names[0].split() if names else []):
                drawn.add('%s/%s' % (package, name))
    return drawn


def test_the_design_page_draws_the_core_as_it_is():
    core = PACKAGE / 'core'
    if not (core / 'mechanics').is_dir():
        return      # the flat core of a branch from before the move
    actual = {'%s/%s' % (p.parent.name, p.name) for p in core.glob('*/*.py')
              if p.name != '__init__.py'}
    drawn = drawn_core((REPO / 'docs' / 'design.md').read_text())
    assert sorted(actual - drawn) == [], 'draw these in docs/design.md, "The core by domain"'
