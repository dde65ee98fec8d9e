"""The mechanism and its motion (floor 1).

The machine's description (``mechanism``: geometry, masses, friction,
stroke) and a run's ``Setup`` (``setup``: the mechanism, gains, task),
orientations (``rotation``: the one place of the convention), inverse
kinematics, leg rates and the Jacobian (``kinematics``, eqs. 2-26), forward
kinematics (``fk``; every assembly mode in ``fk_modes``, tracking in
``fk_tracking``), the assembly mode along a path (``assembly``), the
Newton-Euler dynamics (``dynamics``, eq. 38) and scipy's RK45 compiled
(``dopri``), the small linear solver (``linalg``), the shapes every view
draws (``markers``).

May import: ``plumbing`` (but ``params``), and ``controllers.control``
(eq. 40, floor 0: ``dynamics`` evaluates it inside the ODE).
"""
