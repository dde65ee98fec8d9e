"""The physics and the machine's logic, without ROS (docs/design.md, the layout).

Domain packages, by floor; a module imports from its floor or those below
(test/test_imports.py): ``plumbing`` (0), ``mechanics`` (1), ``controllers``
(2), ``machine`` and ``analysis`` (3), ``scenarios`` (4). ``precompile``
(``python -m stewart63_ros.core.precompile``) compiles every kernel.
"""
