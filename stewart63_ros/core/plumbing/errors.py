"""The core's error for a parameter that cannot be used.

A leaf module (it imports nothing of the package), so that every module that
checks parameters (``params``, ``laws``, ``sensor``, the nodes) raises the
same error without importing each other. ``params.ParameterError`` is this
class, for code that imports it from there.
"""
from __future__ import annotations


class ParameterError(ValueError):
    """A parameter file or value that does not describe a usable mechanism or node.

    The message always starts with the offending key: ``"<key>: <problem>"``.

    Args:
        key: the parameter's name (or ``'params file'`` for the file itself).
        problem: what is wrong with it, for a person to read.
    """

    def __init__(self, key: str, problem: str) -> None:
        super().__init__('%s: %s' % (key, problem))
        self.key = key
        self.problem = problem
