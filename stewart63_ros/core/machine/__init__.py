"""The road to the real machine (floor 3).

The supervisor's trip logic (``supervisor``; its limits, checks and
motions in ``supervisor_limits``, ``supervisor_checks``,
``supervisor_motion``), the CANopen bus's device
configuration, scaling and CiA 402 states (``bus``), calibration
(``calibration``: the fit; ``calibration_plan``: the poses to measure), and
the sensor and actuator faults a run injects (``faults``).

May import: ``plumbing``, ``mechanics``, ``controllers``, and ``analysis``
(same floor). ``faults`` is floor 0 (``plumbing.node_parameters`` checks the
``faults`` parameter with its parser): it imports only floor 0.
"""
