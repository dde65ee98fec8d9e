"""The core's ground floor (0): the words every other floor uses.

Leg and node names (``legs``, ``node_names``), the errors (``errors``), the
declaration of every parameter key, once (``node_parameters``), numba's
switch (``_jit``), time stamps in integer nanoseconds (``stamps``), the
trajectory CSV's columns (``trajectory``), and reading a parameter file
into a validated ``Setup`` (``params``).

May import: nothing of the package but floor 0 (this package, and
``controllers.control`` and ``machine.faults``, which are floor 0 too).
``params`` stands on floor 2: it checks ``control_law`` against
``controllers.laws``, so only floor 2 and above import it.
"""
