"""The plant on the field bus (``io: canopen``): the six legs' CiA 402 drives.

``PlantBus`` is mixed into the plant (nodes/plant.py). Its drives
(canbus/devices.py, ``DeviceSet``) stand on the buses of the device config
(parameter ``bus_config``) instead of the plant's ``leg_lengths`` publisher
and ``leg_forces`` subscription; ``canopen_bridge`` links the bus to the
topics. Ground truth, ``/clock`` and ``/diagnostics`` stay on DDS.

Each SYNC (one on every bus) advances the plant one period: the physics
steps to the SYNC's sample with the forces the drives apply (the target
torques their RPDOs carried, if enabled), then each drive answers with its
TPDO: the sample's position and velocity in encoder counts. The bridge
sends the SYNCs: in lockstep once the controller has answered (so the run
is deterministic), in realtime on the wall clock (the bus's own timing; a
realtime plant that falls behind lets the time of every SYNC that came pass,
with the force held, answers the newest, and counts the others as late).

Before its loop the plant serves the bus from a timer (the bridge brings the
drives up by SDO while the plant waits for its subscribers); while paused
it keeps serving it (NMT, SDO) and holds the SYNCs that come.

Heartbeats (0x1017) keep the clock the bridge judges them on: in lockstep
the run's time (a beat every heartbeat period of samples), in realtime the
wall clock, from the write of 0x1017 on, as a real drive beats: a run that
has not started, or whose SYNCs the bridge skipped after a stall, does not
make the drives look lost.
"""
from __future__ import annotations

import math
import os
import time

import numpy as np

from stewart63_ros.canbus.trace import CycleTrace
from stewart63_ros.core.machine.bus import BusConfigError, load_bus_config
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.runtime.launcher import STOP

#: s: how often the bus is served before the loop starts (SDO answers of the bring-up)
IDLE_SERVICE_PERIOD = 0.002
#: the columns of the realtime drives' per-sample trace (canbus/trace.py)
TRACE_FIELDS = ('k', 'waited', 'sync_seen', 'periods', 'answered', 'cpu', 'thread_cpu', 'armed')
#: ``1`` in the plant's environment: no sample is armed ahead, each is
#: computed when its SYNC is seen (to compare the two); ``0`` or unset: armed
NO_ARM_ENV = 'STEWART63_NO_ARM'
#: s: at its stop, how long the plant's drives go on answering for the bridge's
#: safe stop (its wait for the statuswords and its SDO budget, canbus/master.py)
SAFE_STOP_WAIT = 1.0


class PlantBus:
    """The plant's drives on the bus (see the module's doc)."""

    def init_bus(self):
        """The drives, on the buses of ``bus_config``; a timer serves them
        until the loop starts. ParameterError for a config that cannot work."""
        no_arm = os.environ.get(NO_ARM_ENV, '')
        if no_arm not in ('', '0', '1'):
            raise ParameterError(NO_ARM_ENV, 'must be 1 (no answers armed ahead) or 0, '
                                 'got %r' % no_arm)
        self.arm_ahead = no_arm != '1'
        # lazy: python-can costs 292 ms; only the plant on a bus needs it
        from stewart63_ros.canbus.devices import DeviceSet
        try:
            config = load_bus_config(self.param('bus_config'), self.param('bus_channels'),
                                     self.param('bus_interface'))
        except BusConfigError as exc:
            raise ParameterError('bus_config', str(exc)) from None
        # A drive whose bus_no_boot acts from the run's start stays off.
        off = {leg for state in self.fault_model.states
               if state.fault.kind == 'bus_no_boot' and state.fault.scheduled(0.0)
               for leg in state.fault.legs}
        try:
            devices = DeviceSet(config, booted=[i for i in range(6) if i not in off])
        except ValueError as exc:
            raise ParameterError('bus_interface', str(exc)) from None
        self.get_logger().info('on the bus: %s' % ', '.join(
            '%s = node %d on %s (%s %s)' % (leg.name, leg.node_id, leg.bus,
                                             config.buses[[b.name for b in config.buses]
                                                          .index(leg.bus)].interface,
                                             config.buses[[b.name for b in config.buses]
                                                          .index(leg.bus)].channel)
            for leg in config.legs))
        # lazy: python-can costs 292 ms; only the plant on a bus needs it
        from stewart63_ros.canbus.hub import batched
        # A sample's frames (TPDOs, heartbeats) leave together on each local
        # bus: the bridge wakes once a bus and SYNC, not once a frame.
        self.bus_batch = lambda after_sync=None: batched(devices.buses.values(), after_sync)
        self.bus_timer = self.create_timer(IDLE_SERVICE_PERIOD, self.serve_bus_idle)
        self.syncs_skipped = 0
        self.bus_first = True
        #: realtime: the next sample is computed and its answers armed for
        #: the SYNC to come (``arm_next_sample``), its time stamped here
        self.armed_at = None
        self.samples_armed = 0
        self.arms = False
        return devices

    def serve_bus_idle(self) -> None:
        """Before the loop: NMT and SDO (the bridge's bring-up), and the
        realtime drives' heartbeats."""
        self.devices.poll(0.0)
        self.wall_heartbeats()

    def wall_heartbeats(self) -> None:
        """Realtime: the heartbeats due on the wall clock (lockstep: none
        here; they beat in the run's time, ``bus_sample``)."""
        if self.mode == 'realtime':
            self.devices.heartbeats(time.monotonic())

    def bus_sample(self, lengths, rates, after_sync=None) -> None:
        """Sample ``self.k`` on the bus: faults, heartbeats, each drive's TPDO
        (a leg without a reading, NaN, sends none); ``after_sync``
        ({bus: stamp}): armed for each bus's next SYNC (``hub.batched``)."""
        devices = self.devices
        for event in devices.apply_faults(self.fault_model.bus_active()):
            self.get_logger().warning(event)
        with self.bus_batch(after_sync):
            if self.mode == 'realtime':
                devices.heartbeats(time.monotonic())
            else:
                devices.heartbeats(self.k * self.period)
            for drive in devices.drives:
                i = drive.leg.leg
                if math.isfinite(lengths[i]) and math.isfinite(rates[i]):
                    drive.answer_sync(float(lengths[i]), float(rates[i]))

    def wait_for_sync(self, interruptible: bool = True) -> bool:
        """Serve the bus (and the node's housekeeping) until a SYNC is on
        every bus, or (``interruptible``) a pause, step or reset is asked
        for. False if a stop was requested meanwhile."""
        devices = self.devices
        while not devices.poll(0.0):
            if STOP.requested:
                return False
            if self.hold_due and interruptible and self.armed_at is None:
                return True             # (an armed sample waits for its SYNC first)
            self.wall_heartbeats()
            now = time.monotonic()
            wake = self.housekeeping(now)
            self.forces_in.poll(0.0)            # external_wrench
            if self.armed_at is None and self.arms and not self.hold_due \
                    and devices.next_answer_known():
                self.arm_next_sample()
            devices.poll(max(0.0, min(wake - time.monotonic(), 0.005)))
        return True

    def arm_next_sample(self) -> None:
        """Realtime, once the cycle's torques are in: the step to the next
        SYNC's sample, and the drives' answers armed for that SYNC (the bus
        gives them out the moment it passes, as a drive's SYNC-triggered
        transmit does; canbus/hub.py). The same step and sample as at the
        SYNC (the torques are the ones it would use), taken while waiting:
        a SYNC seen late no longer makes the answer late."""
        self.armed_at = time.monotonic()
        self.force = self.bus_forces()
        self.step()
        self.publish_sample(self.devices.armed_after())
        self.samples_armed += 1

    def run_bus(self, n_samples) -> None:
        """The loop on the bus: a sample per SYNC (see the module's doc)."""
        self.destroy_timer(self.bus_timer)
        trace = CycleTrace.from_env('plant', TRACE_FIELDS, (n_samples or 600_000) + 1) \
            if self.mode == 'realtime' else None
        try:
            self._bus_samples(n_samples, trace)
        finally:
            if trace is not None:
                trace.write()

    def _bus_samples(self, n_samples, trace) -> None:
        devices = self.devices
        self.bus_first = True
        clock = time.monotonic
        arming = self.mode == 'realtime' and devices.can_arm and self.arm_ahead
        while True:
            # the next sample may be armed ahead: realtime, not the run's first
            # (it has no torque yet) nor past its last
            self.arms = arming and not self.bus_first and (n_samples is None or self.k < n_samples)
            stepping = False
            if self.hold_due:
                if not self.sample_boundary():          # pause, step, reset
                    return
                stepping = self.hold_due                # ~/step let this sample through
            waited = clock()
            if not self.wait_for_sync(interruptible=not stepping):
                return
            sync_seen = clock()
            armed_at, self.armed_at = self.armed_at, None
            if self.hold_due and not stepping and armed_at is None:
                continue
            periods = 1
            if self.mode == 'realtime':
                # Behind the bus: the time of every SYNC that came passes (with
                # the force held), and the newest one is answered.
                periods = min(devices.syncs.values())
                if n_samples is not None:
                    periods = max(1, min(periods, n_samples - self.k))
                self.syncs_skipped += periods - 1
                self.late += periods - 1
                for name in devices.syncs:
                    devices.syncs[name] -= periods - 1
            devices.take_sync()
            # (an armed sample answered the first of these SYNCs)
            steps = periods - 1 if armed_at is not None else periods
            if not self.bus_first and steps:
                self.force = self.bus_forces()
                for _ in range(steps):
                    self.step()
            self.bus_first = False
            if armed_at is None or steps:
                self.publish_sample()
            if trace is not None:
                trace.add(self.k, waited, sync_seen, periods,
                          clock() if armed_at is None or steps else armed_at,
                          time.process_time(), time.thread_time(), armed_at is not None)
            if n_samples is not None and self.k >= n_samples:
                return

    def bus_forces(self):
        return np.array(self.devices.forces())

    def restart_on_bus(self) -> None:
        """A reset (``~/reset``): the SYNCs that came before it are not the new run's."""
        for name in self.devices.syncs:
            self.devices.syncs[name] = 0
        self.bus_first = True

    def serve_while_holding(self, until: float) -> None:
        """Held (paused, reset): the node's waits, and the bus's NMT and SDO
        (the SYNCs that come are counted, answered once the run goes on)."""
        super().serve_while_holding(min(until, time.monotonic() + 0.01)
                                    if getattr(self, 'devices', None) is not None else until)
        if getattr(self, 'devices', None) is not None:
            self.devices.poll(0.0)
            self.wall_heartbeats()

    def next_sample(self) -> int:
        """The sample the loop publishes next: on the bus the physics steps at
        the SYNC, so a plant held between two samples has not stepped yet."""
        if getattr(self, 'devices', None) is None:
            return super().next_sample()
        return self.k if self.bus_first or self.forces_in is None else self.k + 1

    def report_bus(self) -> None:
        devices = self.devices
        values = self.health.values
        if self.holding:
            values['sample'] = self.next_sample()
        values['bus_frames_in'] = devices.frames_in
        values['bus_frames_out'] = devices.frames_out
        values['bus_syncs_skipped'] = self.syncs_skipped
        values['bus_samples_armed'] = self.samples_armed
        # what the drives apply now (zero once the bridge withholds torque)
        values['bus_forces'] = [round(f, 1) for f in devices.forces()]
        values['bus_drives'] = ', '.join(
            '%s: %s%s' % (d.leg.name, 'off' if d.off else d.nmt.lower(),
                          '' if d.off else ' ' + d.drive.state.lower())
            for d in devices.drives)

    def close(self):
        """Drives outlive their master: at the plant's stop (the end of its
        duration, a signal) its drives go on answering until the bridge has
        left them safe (NMT pre-operational, its safe stop's last step), at
        most SAFE_STOP_WAIT s; so the bridge's stop is confirmed by them
        (docs/bus.md, "Stopping"), however the two are stopped."""
        devices = getattr(self, 'devices', None)
        deadline = time.monotonic() + SAFE_STOP_WAIT
        while devices is not None and time.monotonic() < deadline and any(
                not d.off and d.nmt == 'OPERATIONAL' for d in devices.drives):
            devices.poll(0.005)
        super().close()

    def close_bus(self) -> None:
        devices = getattr(self, 'devices', None)
        if devices is not None:
            devices.close()
