"""An example of a user's own control law: ``control_law: stewart63_ros.examples.my_law:LegPD``.

The interface every law follows (docs/controllers.md, docs/interface.md "Control laws"):

- ``__init__(self, mech, params)``: ``mech`` is the validated ``Mechanism``
  (the machine: geometry, masses, ``max_force``, ...), ``params`` the
  controller's parameter dictionary (the gains ``kp``, ``kv``, the setpoint and
  initial state, every other key). A law reads its own keys there, named with a prefix of
  its own (here ``legpd_kp``, ``legpd_kv``) and lists them in ``parameters``:
  the controller then lets them change at run time (``ros2 param set``)
  through ``set_parameter``.
- ``__call__(self, t, lengths, rates, ref)``, once per sample: sample time t
  [s], measured leg lengths L [m] and rates dL/dt [m/s] (numpy arrays of 6),
  and the reference sample ``ref`` (``ref.lengths``, ``ref.rates``,
  ``ref.position``, ``ref.rotation``, ``ref.velocity``, ``ref.omega``,
  ``ref.acceleration``, ``ref.alpha``; valid during the call only). Returns
  six piston forces [N]; the controller saturates them at +-max_force. An
  exception, or a NaN, withholds the forces and reports ERROR on
  /diagnostics; the node stays up.
- ``set_parameter(self, name, value)``: raise ``ValueError`` with the reason
  to refuse a value (nothing changes then).

This one is eq. (40) with its own gains, towards the reference's leg lengths
and rates: F = Kp (L_ref - L) + Kv (dL_ref/dt - dL/dt).
"""
import numpy as np


class LegPD:
    parameters = ('legpd_kp', 'legpd_kv')

    def __init__(self, mech, params):
        self.kp = self._gains('legpd_kp', params.get('legpd_kp', params['kp']))
        self.kv = self._gains('legpd_kv', params.get('legpd_kv', params['kv']))

    @staticmethod
    def _gains(name, value):
        arr = np.array(value, dtype=float).ravel()
        if arr.shape != (6,) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
            raise ValueError('%s must be six finite gains >= 0, got %r' % (name, value))
        return arr

    def set_parameter(self, name, value):
        gains = self._gains(name, value)
        if name == 'legpd_kp':
            self.kp = gains
        else:
            self.kv = gains

    def __call__(self, t, lengths, rates, ref):
        return self.kp * (ref.lengths - lengths) + self.kv * (ref.rates - rates)


class Failing:
    """A law that raises after ``failing_after`` s (for the tests of the error path)."""

    parameters = ()

    def __init__(self, mech, params):
        self.after = float(params.get('failing_after', 0.0))
        self.kp = np.array(params['kp'], float)

    def __call__(self, t, lengths, rates, ref):
        if t >= self.after:
            raise RuntimeError('this law fails on purpose')
        return self.kp * (ref.lengths - lengths)
