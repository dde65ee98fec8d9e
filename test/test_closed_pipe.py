"""Every executable ends quietly when the reader of its output goes away.

``analyze modes | head -3`` used to end in a BrokenPipeError traceback. One
mechanism, ``tools.cli.quiet_on_closed_pipe``, wraps the ``main`` of every
console script of setup.py (checked here for all of them), and a few real
commands are run with their standard output closed before they write.
"""
from __future__ import annotations

import importlib
import re
import subprocess
from pathlib import Path

import pytest
from ros_harness import PYTHON

REPO = Path(__file__).resolve().parents[1]
BIN = Path(PYTHON).parent


def console_scripts() -> dict:
    """{name: 'module:function'} of setup.py's console scripts."""
    text = (REPO / 'setup.py').read_text()
    scripts = text[text.index("'console_scripts'"):]
    scripts = scripts[:scripts.index(']')]     # not the can.interface or pytest11 groups
    return dict(re.findall(r"'(\w+) = ([\w.]+:\w+)'", scripts))


def test_every_console_script_goes_through_the_shared_guard():
    scripts = console_scripts()
    assert len(scripts) >= 12
    for name, target in scripts.items():
        module, function = target.split(':')
        main = getattr(importlib.import_module(module), function)
        assert getattr(main, 'quiet_on_closed_pipe', False), \
            '%s (%s) does not end quietly on a closed pipe' % (name, target)


def run_with_stdout_closed(args, timeout=120):
    """Run ``args`` with a pipe for stdout whose reading end is closed at once
    (what ``| head -1`` does once it has its line); (status, stderr)."""
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    try:
        _, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err.decode()


@pytest.mark.parametrize('argv', [
    ['analyze', 'modes'],
    ['analyze', 'modes', '--json'],
    ['sim', '--duration', '0.05', '--no-figure', '--out', '{tmp}'],
    ['sweep', '--runs', '2', '--duration', '0.05', '--workers', '1', '--no-figure',
     '--out', '{tmp}'],
])
def test_a_closed_output_pipe_ends_quietly(argv, tmp_path):
    args = [str(BIN / argv[0])] + [a.format(tmp=tmp_path) for a in argv[1:]]
    status, err = run_with_stdout_closed(args)
    assert 'Traceback' not in err and 'BrokenPipeError' not in err, err
    assert status == 141, (status, err)
