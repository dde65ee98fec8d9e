"""The plant's faults and simulation control (pause, step, reset): the node's side.

``PlantControl`` is mixed into ``PlantNode``; the fault logic itself is the
core's (core/machine/faults.py), shared with ``sim``. What this adds to the node:

- the parameter ``faults`` (a list of fault strings), also changed at run
  time (``ros2 param set /plant faults "[...]"``): a bad string refuses the
  whole change with the reason, the faults in force stay as they were;
- the faults on /diagnostics: each under ``fault: <fault>`` (scheduled,
  active since, ended), WARN naming the active ones, a status at once when
  one starts or ends;
- the services ``~/pause`` (std_srvs/SetBool), ``~/reset`` (std_srvs/Trigger)
  and, in lockstep, ``~/step`` (std_srvs/Trigger: ``step_count`` samples,
  then paused again). They act between two samples (``sample_boundary``,
  called by the plant's loops when ``hold_due`` is set); while paused the
  loop keeps serving the executor (services, parameters, timers) and stop
  signals, sleeping in between.

The plant announces ``run: paused`` and ``run: reset`` on /diagnostics before
its samples stop, as it announces ``run: ended``: the controller's watchdog
then takes the silence for what it is.
"""
from __future__ import annotations

import time

import numpy as np
from std_srvs.srv import SetBool, Trigger

from stewart63_ros.core.controllers.sensor import SensorModel
from stewart63_ros.core.controllers.simulate import initial_state
from stewart63_ros.core.machine.faults import FaultError, FaultModel
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.runtime.checks import RESTART_PAUSE, StaleForce
from stewart63_ros.runtime.launcher import STOP

#: s: the quiet before the first sample of a new run (``~/reset``): longer
#: than the nodes' RESTART_PAUSE, so their stamp gates accept the new run's
#: stamps (back at 0 in lockstep) as a restarted source's.
RESET_QUIET = 2.0 * RESTART_PAUSE
#: s: the longest a paused loop sleeps between two looks at its flags.
HOLD_POLL = 0.1
_NO_FORCE = np.zeros(6)


class PlantControl:
    """Faults, pause, step and reset for ``PlantNode`` (see the module's doc)."""

    def init_control(self) -> None:
        """Called by the plant's constructor once its model and loop state exist."""
        try:
            self.fault_model = FaultModel(self.param('faults'), self.rate,
                                          self.param('sensor_seed'), bus=self.on_bus)
        except FaultError as exc:       # a bus fault without the bus
            raise ParameterError('faults', str(exc)) from None
        self.force_is_stale = StaleForce(self.param('force_stale_ms'), self.health.values,
                                         self.get_logger().error)
        self.answer_every_sample = self.param('answer_every_sample')
        # The sensors' hidden zero and the one a homing set (supervisor).
        self.homing_offset = self.param('homing_offset')
        self.set_homed_offset(self.param('homed_offset'))
        self.tunable('homed_offset', self.set_homed_offset)
        self.sample_complete = True     # the last sample carried all six readings
        self.step_count = self.param('step_count')
        self.tunable('faults', self.set_faults)
        self.tunable('step_count', self.set_step_count)
        self.paused = False
        self.step_left = 0              # samples a ~/step still lets through
        self.reset_requested = False
        self.resetting = False          # restart_run's quiet: the new run's number is out
        self.holding = False            # the loop waits between two samples
        self.hold_due = False           # the loop must call sample_boundary
        self.run_number = 1
        self.resets = 0
        self.ended = False
        self.health.values['run'] = 'starting'
        self.health.values['run_number'] = self.run_number
        self.health.values['resets'] = self.resets
        self.create_service(SetBool, '~/pause', self.on_pause)
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.create_service(Trigger, '~/step', self.on_step)

    # -- faults ---------------------------------------------------------------------
    def set_faults(self, value) -> None:
        """Run-time ``faults`` (parsed by their declaration): in force together,
        or ParameterError (a new fault whose times are past, a bus fault
        without the bus: nothing changes)."""
        try:
            events = self.fault_model.set_faults(value, next_sample=self.next_sample())
        except FaultError as exc:
            raise ParameterError('faults', str(exc)) from None
        for event in events:
            self.get_logger().warning(event)
        if self.started:
            self.report()

    def set_homed_offset(self, value) -> None:
        """``homed_offset`` (a homing's result): the readings from the next sample
        on are true + ``homing_offset`` - this."""
        shift = self.homing_offset - value
        self.encoder_shift = shift if shift.any() else None
        if value.any() or self.homing_offset.any():     # (a machine with homing)
            self.health.values['homed_offset'] = np.round(value, 6).tolist()

    def set_step_count(self, value) -> None:
        self.step_count = value

    def begin_faults(self) -> None:
        """Sample ``self.k`` begins: faults that start or end on it are logged
        and reported at once (so a recording holds each change)."""
        events = self.fault_model.begin(self.k)
        if events:
            for event in events:
                self.get_logger().warning(event)
            self.report()

    def applied_force(self) -> np.ndarray:
        """The held force as the pistons apply it (actuator faults); zero once
        it answers a sample more than ``force_stale_ms`` before this one (fail
        safe: a supervisor or controller that died leaves no force acting)."""
        if self.force_is_stale.stale_ns and self.force_is_stale(
                self.k, int(round(self.sample_time(self.k) * 1e9)), self.force_ns):
            return self.fault_model.actuate(_NO_FORCE)
        return self.fault_model.actuate(self.force)

    def report_faults(self) -> None:
        """The faults into the next status: ``fault: <fault>`` values, and the
        active ones in the WARN message."""
        h = self.health
        for key in [k for k in h.values if k.startswith('fault: ')]:
            del h.values[key]
        h.values.update(self.fault_model.status_values())
        active = self.fault_model.active_text()
        if active:
            h.warning = '; '.join(m for m in (h.warning, active) if m)

    # -- services ----------------------------------------------------------------------
    def next_sample(self) -> int:
        """The sample the loop publishes next (a request acts before it; during
        a reset's quiet, the new run's first)."""
        if self.resetting:
            return 0
        return self.k if self.holding or self.forces_in is None else self.k + 1

    def on_pause(self, request, response):
        """``~/pause``: data true pauses before the next sample, false resumes."""
        response.success = True
        if self.ended:
            response.success, response.message = False, 'the run has ended'
        elif request.data:
            if self.paused and not self.step_left:
                response.message = 'already paused before sample %d' % self.next_sample()
            else:
                self.paused, self.step_left, self.hold_due = True, 0, True
                response.message = 'paused before sample %d (t = %g s)' % (
                    self.next_sample(), self.next_sample() * self.period)
        elif self.paused:
            self.paused, self.step_left = False, 0
            response.message = 'resumed at sample %d' % self.next_sample()
        else:
            response.message = 'not paused'
        self.get_logger().info('~/pause %s: %s' % (request.data, response.message))
        return response

    def on_step(self, request, response):
        """``~/step`` (lockstep, paused): ``step_count`` samples, then paused again."""
        response.success = False
        if self.ended:
            response.message = 'the run has ended'
        elif self.mode != 'lockstep':
            response.message = ('~/step needs clock_mode lockstep; in realtime pause and '
                                'resume with ~/pause')
        elif not self.paused:
            response.message = 'not paused: pause first (~/pause with data: true)'
        elif self.step_left:
            response.message = 'still stepping: %d samples left' % self.step_left
        else:
            first = self.next_sample()
            self.step_left, self.hold_due = self.step_count, True
            response.success = True
            response.message = ('stepping %d samples (%d to %d), then paused before sample %d'
                                % (self.step_count, first, first + self.step_count - 1,
                                   first + self.step_count))
        self.get_logger().info('~/step: %s' % response.message)
        return response

    def on_reset(self, request, response):
        """``~/reset``: a new run from the parameter file's initial state.

        A reset is pending from its answer until the new run's state is set
        (after the quiet): a second one meanwhile is refused.
        """
        response.success = False
        if self.ended:
            response.message = 'the run has ended'
        elif self.reset_requested:
            response.message = 'a reset is already pending (run %d starts after the quiet)' % (
                self.run_number + (0 if self.resetting else 1))
        else:
            self.reset_requested, self.hold_due = True, True
            response.success = True
            last = self.next_sample() - 1
            response.message = ('resetting %s: run %d starts from the initial state at sample 0 '
                                'after %g s of quiet%s' % (
                                    'after sample %d' % last if last >= 0 else
                                    'before the first sample of run %d' % self.run_number,
                                    self.run_number + 1, RESET_QUIET,
                                    ', paused' if self.paused else ''))
        self.get_logger().info('~/reset: %s' % response.message)
        return response

    # -- between two samples -------------------------------------------------------------
    def announce_run(self, state: str) -> None:
        """``run: <state>`` on /diagnostics at once (running, paused, reset)."""
        if self.health.values.get('run') != state:
            self.health.values['run'] = state
            if self.started:
                self.report()

    def serve_while_holding(self, until: float) -> None:
        """One wait of the held loop: the node's housekeeping (services,
        parameters, timers), then sleep until it is due again (at most
        ``until``, HOLD_POLL); forces that come in meanwhile are taken."""
        now = time.monotonic()
        wake = min(self.housekeeping(now), until, now + HOLD_POLL)
        self.forces_in.poll(max(0.0, wake - time.monotonic()))

    def sample_boundary(self) -> bool:
        """Between two samples, when ``hold_due``: reset, pause, step.

        Returns:
            False when a stop was requested meanwhile (the loop ends).
        """
        held_since = None
        state = 'running'
        realtime_base = self.t0_mono
        # A paused realtime plant integrates nothing: on_forces advances the
        # physics only while t0_mono is set.
        self.t0_mono = None
        try:
            while not STOP.requested:
                if self.reset_requested:
                    self.restart_run(held_since)
                    held_since = time.monotonic()
                    continue
                if not self.paused:
                    self.hold_due = False
                    break
                if self.step_left:
                    self.step_left -= 1
                    state = 'stepping'
                    break
                if held_since is None:
                    held_since = time.monotonic()
                    self.holding = True
                    self.get_logger().info('paused before sample %d' % self.k)
                self.announce_run('paused')
                self.serve_while_holding(time.monotonic() + HOLD_POLL)
            else:
                return False
        finally:
            self.holding = False
            self.t0_mono = realtime_base
        if held_since is not None and self.mode == 'realtime':
            # The wall-clock schedule goes on from now: sample k is due at once,
            # and its stamp (wall time) continues from the present.
            self.t0_mono = time.monotonic() - self.k * self.period
            self.t0_wall = time.time() - self.k * self.period
        self.announce_run(state)
        return True

    def restart_run(self, quiet_since) -> None:
        """``~/reset``: quiet for RESET_QUIET (announced ``run: reset``), then
        the initial state of the parameter file at sample 0 of a new run.
        The reset stays pending (``reset_requested``) until then."""
        self.holding = True
        self.resetting = True
        # The new run's number goes out with the announcement, a quiet
        # second before its first sample (the controller restarts its
        # reference on it; in realtime the stamps do not jump back).
        self.run_number += 1
        self.resets += 1
        self.health.values['run_number'] = self.run_number
        self.health.values['resets'] = self.resets
        # The old run is over: its faults end with it, the new run's are
        # scheduled from its t = 0 (a fault set during the quiet counts from there).
        self.fault_model.reset()
        self.announce_run('reset')
        until = (quiet_since or time.monotonic()) + RESET_QUIET
        try:
            while not STOP.requested and time.monotonic() < until:
                self.serve_while_holding(until)
        finally:
            self.reset_requested = self.resetting = False
        if STOP.requested:
            return
        self.y = initial_state(self.setup.task)
        self.k = 0
        self.t_phys = 0.0
        self.force = np.zeros(6)
        self.force_ns = None
        self.sent_wall.clear()
        self.sensor = SensorModel(self.params)      # its noise starts over, as on a restart
        if self.tracking is not None:
            self.tracking.reset()
        # The new run's answers carry stamps from 0 again (lockstep): not from the past.
        self.force_gate.last_ns = None
        if self.devices is not None:
            self.restart_on_bus()       # plant_bus.py
        self.get_logger().warning('reset: run %d starts from the initial state'
                                  % self.run_number)
