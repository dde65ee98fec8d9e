"""An example law with a fault detector.

    control_law: stewart63_ros.examples.fault_detector:CheckedPD

Eq. (40) towards the reference (as ``pd``), and a check of every leg's
sensor: over the last ``fd_window`` samples, the change of the measured
length must agree with the integral of the rate the same sensor reports
(trapezoids over the sample times), within ``fd_threshold`` metres. A stuck
sensor (its length frozen while the rate it last gave says the leg moves), a
delayed or biased length that changes under a rate that does not (a fault
switched on mid-motion) fail the check.

On a failed check the law raises ``SensorFault`` naming the leg and the
mismatch; the controller then withholds its forces and reports ERROR on
/diagnostics with that text (README, "Control laws": a law that raises). The
trip latches: every later sample raises again, until the law is built anew
(``ros2 param set /controller control_law ...`` or a restart).

With the supervisor in the rig (``rig --supervisor``) that ERROR is the
law's request to trip: the supervisor, waiting for the forces of the very
sample the law refused, trips on it (cause ``diagnostics_error``, naming the
controller and this message) and brings the platform down
(docs/supervisor.md, "How a user's law asks for a trip").

A gap in the samples (a withheld or refused sample, a pause, a new run whose
time starts again) restarts the window instead of integrating across it.

Parameters (run-time changeable, ``ros2 param set``): ``fd_window`` (samples,
integer >= 2, default 20), ``fd_threshold`` (m, > 0, default 0.002); the
gains are ``kp`` and ``kv`` of the parameter file.
"""
from collections import deque

import numpy as np

from stewart63_ros.core.plumbing.params import LEG_NAMES


class SensorFault(RuntimeError):
    """A leg sensor whose length and rate disagree."""


class CheckedPD:
    parameters = ('fd_window', 'fd_threshold')

    def __init__(self, mech, params):
        self.kp = np.array(params['kp'], dtype=float)
        self.kv = np.array(params['kv'], dtype=float)
        self.window = self._window(params.get('fd_window', 20))
        self.threshold = self._threshold(params.get('fd_threshold', 0.002))
        self.samples = deque(maxlen=self.window + 1)     # (t, lengths, rates)
        self.integral = deque(maxlen=self.window)       # rate integral per interval
        self.period = None      # the usual sample interval [s]
        self.tripped = ''

    @staticmethod
    def _window(value):
        if isinstance(value, bool) or not isinstance(value, int) or value < 2:
            raise ValueError('fd_window must be an integer >= 2 (samples), got %r' % (value,))
        return value

    @staticmethod
    def _threshold(value):
        value = float(value)
        if not (np.isfinite(value) and value > 0):
            raise ValueError('fd_threshold must be a length > 0 [m], got %r' % (value,))
        return value

    def set_parameter(self, name, value):
        if name == 'fd_window':
            self.window = self._window(value)
            self.samples = deque(maxlen=self.window + 1)
            self.integral = deque(maxlen=self.window)
        else:
            self.threshold = self._threshold(value)

    def check(self, t, lengths, rates):
        """Add this sample to the window; SensorFault if a leg disagrees."""
        if self.samples:
            t_prev, l_prev, r_prev = self.samples[-1]
            dt = t - t_prev
            if dt <= 0 or (self.period is not None and dt > 3 * self.period):
                self.samples.clear()        # a gap or a new run: start the window again
                self.integral.clear()
            else:
                self.period = dt if self.period is None else min(self.period, dt)
                self.integral.append(0.5 * dt * (r_prev + rates))
        self.samples.append((t, np.array(lengths, float), np.array(rates, float)))
        if len(self.samples) <= self.window:
            return
        moved = self.samples[-1][1] - self.samples[0][1]
        integrated = np.sum(self.integral, axis=0)
        mismatch = np.abs(moved - integrated)
        worst = int(np.argmax(mismatch))
        if mismatch[worst] > self.threshold:
            self.tripped = (
                'sensor fault on %s at t = %.4f s: its length moved %.2f mm in %.4f s '
                'while its rate says %.2f mm (mismatch %.2f mm > fd_threshold %.2f mm)' % (
                    LEG_NAMES[worst], t, 1e3 * moved[worst],
                    self.samples[-1][0] - self.samples[0][0], 1e3 * integrated[worst],
                    1e3 * mismatch[worst], 1e3 * self.threshold))

    def __call__(self, t, lengths, rates, ref):
        if not self.tripped:
            self.check(t, lengths, rates)
        if self.tripped:
            raise SensorFault(self.tripped)
        return self.kp * (ref.lengths - lengths) + self.kv * (ref.rates - rates)
