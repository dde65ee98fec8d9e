"""Control (floor 2): eq. (40), the laws, references, the loop run offline.

Eq. (40) written once (``control``, floor 0), the laws and their interface
(``laws``: pd, pd_gravity, computed_torque, a user's class), reference
motions (``reference``), the sensor model's noise and delay (``sensor``),
and the plant and a law integrated together without DDS (``simulate``:
``sim``'s, the sweep's, the scenarios').

May import: ``plumbing``, ``mechanics``, and ``machine.faults`` (floor 0).
``control`` imports only floor 0.
"""
