"""canopen_bridge: the master of the legs' CANopen buses, linking them to the topics.

At start-up it computes the bus load of its configuration (refused over 100 %,
with the rates that fit), resets every drive (NMT), and brings each one up
as it boots: PDO mapping by SDO from its EDS, heartbeat, mode 10 (cyclic
synchronous torque), the CiA 402 state machine to OPERATION ENABLED, NMT
start (canbus/master.py). Then, per sample: a SYNC on every bus; each
drive's TPDO (position 0x6064, velocity 0x606C, in counts) becomes
``leg_lengths`` [m, m/s] stamped with the SYNC's time; the ``leg_forces``
answer becomes each drive's target torque 0x6071 [per mille of 0x6076].

clock_mode ``lockstep``: the next SYNC goes out once the controller has
answered (or ``force_timeout`` passed), so a run through the bus is
deterministic; stamps are the simulated time k / sensor_rate. ``realtime``:
SYNC on the wall clock, forces written as they arrive; an answer that has
not arrived by the next SYNC is a missed cycle, counted. A sample holds only
the TPDOs received in its SYNC's window (nodes/bridge_cycles.py).

On every way out (the end of ``duration``, SIGINT, SIGTERM, an exception)
the drives are left safe: zero torque, disable operation and shutdown
(READY TO SWITCH ON), NMT pre-operational; a lost controller shuts them
down until it answers again. docs/bus.md, "Stopping".

With ``rig --supervisor`` the supervisor answers every sample
(``answer_every_sample``); a force that answers a sample more than
``force_stale_ms`` old is not sent, zero torque is (a supervisor that died
leaves the drives without torque); ``homed_offset`` (set by the
supervisor's homing) is written to each drive's home offset 0x607C by SDO.

A drive that does not boot, goes silent (no TPDO, no heartbeat), sends an
EMCY, or falls into FAULT is named on ``/diagnostics`` (ERROR) at the cycle
it is seen, and torque is withheld from all drives (zero torque to those
that listen) until every drive is back: a drive that boots again is brought
up again, a drive in FAULT gets a fault reset and is re-enabled.
docs/bus.md.
"""
from __future__ import annotations

import math
import sys
import time
import types

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState

from stewart63_ros import topics
from stewart63_ros.canbus.busload import WARNING_PREFIX, WireLoad
from stewart63_ros.canbus.master import Master
from stewart63_ros.canbus.sync import silent_cycles
from stewart63_ros.core.machine.bus import BusConfigError, BusLoadError, load_bus_config
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.exits import quiet_on_closed_pipe
from stewart63_ros.nodes.bridge_cycles import CONTROLLER_LOST_MIN, SYNC_WINDOW, BridgeCycles
from stewart63_ros.runtime import wire
from stewart63_ros.runtime.base import RigNode
from stewart63_ros.runtime.checks import (
    RESTART_PAUSE,
    StaleForce,
    StampGate,
    ros_time,
)
from stewart63_ros.runtime.handshake import plant_run
from stewart63_ros.runtime.launcher import run
from stewart63_ros.runtime.lockstep import PeerWindow
from stewart63_ros.runtime.startup import PlantStartup

#: s: while waiting for the drives' boot-ups, how often the bridge says what it waits for
BOOT_REPORT_PERIOD = 5.0


class NoDriveAnswers(RuntimeError):
    """No drive of the config sent a boot-up: one line saying what was awaited."""


class BridgeNode(BridgeCycles, RigNode):
    """The bridge (see the module's doc; its loops: nodes/bridge_cycles.py)."""

    def __init__(self, options):
        super().__init__('canopen_bridge')
        self.rate = self.param('sensor_rate')
        self.period = 1.0 / self.rate
        self.period_ns = int(round(1e9 / self.rate))
        self.mode = self.param('clock_mode')
        self.duration = self.param('duration')
        self.force_timeout = self.param('force_timeout')
        self.lost_after = max(self.force_timeout, CONTROLLER_LOST_MIN)
        self.bus_timeout = self.param('bus_timeout')
        self.boot_timeout = self.param('boot_timeout')
        # With the supervisor in the rig (rig --supervisor): it answers every
        # sample, and a force it no longer sends goes stale: zero torque.
        self.answer_every_sample = self.param('answer_every_sample')
        self.force_is_stale = StaleForce(self.param('force_stale_ms'), self.health.values,
                                         self.get_logger().error)
        self.homed_offset = self.param('homed_offset')
        self.tunable('homed_offset', self.set_homed_offset)
        try:
            config = load_bus_config(self.param('bus_config'), self.param('bus_channels'),
                                     self.param('bus_interface'), self.param('bus_bitrate'))
        except BusConfigError as exc:
            raise ParameterError('bus_config', str(exc)) from None
        self.config = config
        try:
            self.master = Master(config, self.rate, log=self.get_logger().info)
        except BusLoadError as exc:
            raise ParameterError('bus_bitrate', str(exc)) from None
        except BusConfigError as exc:
            raise ParameterError('bus_config', str(exc)) from None
        except ValueError as exc:      # the interface or its channel
            raise ParameterError('bus_interface', str(exc)) from None
        for load in config.loads(self.rate):
            self.get_logger().info(load.text())
        # the load on the wire beside the planned one; unknown COB-IDs (busload.py)
        self.wire = WireLoad(config, self.rate)
        self.wire.attach(self.master.networks)
        # the synchronous window into each drive that has 0x1007 (lockstep: none,
        # a SYNC's window lasts until every drive has answered)
        self.master.sync_window_us = int(SYNC_WINDOW * 1e6 / self.rate) \
            if self.mode == 'realtime' else 0
        if self.mode == 'realtime':     # lockstep: a miss has waited bus_timeout already
            self.master.tpdo_error_cycles = silent_cycles(self.param('tpdo_missing_error_ms'),
                                                          self.rate)
            self.master.clock = 'wall'  # heartbeats judged on their reception times
        self.late_tpdo = ''             # the last TPDO that missed its cycle (realtime)
        # The plant's start-up waits, now the bridge's: it publishes the samples.
        self.lengths_subscribers = self.param('lengths_subscribers')
        self.lengths_peers = self.peer_names('lengths_peers')
        self.peers = None
        lockstep_peers = self.peer_names('lockstep_peers')
        if lockstep_peers and self.mode == 'lockstep':
            self.peers = PeerWindow(self, lockstep_peers, self.param('lockstep_window'),
                                    self.period_ns, self.param('lockstep_peer_timeout'))
        pub = self.publisher(JointState, topics.LEG_LENGTHS, topics.STREAM_PUB)
        self.outputs = types.SimpleNamespace(pub_lengths=pub)
        self.send_lengths = self.health.sender(topics.LEG_LENGTHS, pub)
        self.lengths_out = wire.JointStateTemplates(('position', 'velocity')).get('base')
        wire.warm_up(('effort',))
        self.force_gate = StampGate(RESTART_PAUSE)
        self.sub_forces = self.create_subscription(JointState, topics.LEG_FORCES,
                                                   self.on_forces, topics.LATEST_SUB, raw=True)
        self.watch_source(self.sub_forces, topics.LEG_FORCES, self.force_gate)
        self.plant_startup = PlantStartup(self)
        # The plant's run on /diagnostics: paused or reset, its drives hold the SYNC.
        self.plant_node = topics.node_full_name(self.get_namespace(), 'plant')
        self.plant_status = topics.status_name(self.plant_node)
        self.plant_run = 'running'
        self.plant_run_number = None
        self.new_run = False
        self.sub_diagnostics = self.create_subscription(
            DiagnosticArray, topics.DIAGNOSTICS, self.on_diagnostics, topics.DIAGNOSTICS_QOS)
        self.force = None
        self.force_ns = None
        self.force_at = 0.0             # time.monotonic() the newest force came
        self.lost_controller = False
        self.timeouts_in_a_row = 0      # lockstep: samples the controller did not answer
        self.schedule = None            # realtime: the SYNC clock (bridge_cycles)
        self.stopped_drives = None      # the drives' states after the safe stop
        self.sent_wall = {}
        self.errors: list[str] = []
        self.k = 0
        self.missed = 0
        self.timeouts = 0
        self.cycles = 0
        self.bus_wait_s = 0.0           # SYNC to the last TPDO (lockstep): the plant's step
        self.answer_wait_s = 0.0        # leg_lengths to leg_forces: the controller
        self.forces_in = None

    # -- inputs -----------------------------------------------------------------------------
    def on_forces(self, data: bytes, info):
        received = time.perf_counter()
        taken = self.take_forces(data, info, self.force_gate)
        if taken is None:
            return
        self.force_ns, self.force = taken
        self.force_at = time.monotonic()
        sent = self.sent_wall.pop(self.force_ns, None)
        if sent is not None:
            self.health.latency.add(received - sent)
        if self.mode == 'realtime':         # on the bus at once; applied at the next SYNC
            self.write_torques(self.k, self.force_ns)

    def on_diagnostics(self, msg):
        said = plant_run(msg, self.plant_status)
        self.plant_run = said.get('run', self.plant_run)
        number = said.get('run_number')
        if number is not None:
            if self.plant_run_number is not None and number != self.plant_run_number:
                self.new_run = True
            self.plant_run_number = number

    def startup_missing(self) -> list[str]:
        """What the bridge waits for before SYNC 0: the plant's wait
        (``PlantStartup``), and in lockstep the plant's /diagnostics writer.
        Its run word (paused, reset) is what tells drives that hold the SYNC
        from silent ones; a word sent before that match is lost, and a paused
        plant was then taken for a pulled cable (NaN samples after
        ``bus_timeout``, test_sim_control_dds's pause over the bus at -n 2)."""
        out = self.plant_startup.missing()
        if self.mode == 'lockstep':
            shown = {topics.endpoint_node_name(info) for info in
                     self.get_publishers_info_by_topic(self.sub_diagnostics.topic_name)}
            if self.plant_node not in shown:
                out.append('%s: no publisher from %s yet (its run word: paused, reset)'
                           % (self.sub_diagnostics.topic_name, self.plant_node))
        return out

    def set_homed_offset(self, value) -> None:
        """``homed_offset`` (a homing's result, set by the supervisor): each
        drive's home offset 0x607C by SDO, so its next TPDO reads homed;
        ParameterError naming the drive that did not take it."""
        import canopen  # lazy: optional: canopen costs 273 ms; the simulated bus runs without it
        counts = []
        for link in self.master.links:
            try:
                counts.append(self.master.write_home_offset(link, float(value[link.leg.leg])))
            except (BusConfigError, canopen.SdoCommunicationError, canopen.SdoAbortedError,
                    OSError) as exc:
                raise ParameterError('homed_offset', '%s: home offset 0x607C not written: %s'
                                     % (link.name, exc)) from None
        self.homed_offset = value
        self.health.values['home_offset_counts'] = counts
        self.get_logger().info('home offsets 0x607C written: %s counts' % counts)

    # -- the bus ----------------------------------------------------------------------------
    def bring_up(self) -> None:
        """Reset every drive and bring up those that boot within ``boot_timeout``."""
        master = self.master
        master.reset_all()
        started = time.monotonic()
        missing = master.links
        while missing:          # says at once what it waits for, and again every few s
            waited = time.monotonic() - started
            self.get_logger().info('waiting %s for the boot-up of %s' % (
                'up to %g s (boot_timeout)' % self.boot_timeout if missing is master.links
                else '(%.0f of %g s)' % (waited, self.boot_timeout), master.describe(missing)))
            missing = master.wait_for_boot(min(BOOT_REPORT_PERIOD,
                                               self.boot_timeout - waited))
            if time.monotonic() - started >= self.boot_timeout:
                break
        if len(missing) == len(master.links):
            raise NoDriveAnswers(
                'no drive answered: no boot-up within %g s (boot_timeout) of an NMT reset '
                'from %s: drives powered, bus wired and terminated, bitrate right?'
                % (self.boot_timeout, master.describe(missing)))
        for link in master.links:
            if link.booted:
                master.bring_up(link)
        # A drive that booted again meanwhile (a reset that reached it after its
        # power-on boot-up) is configured again now, not at the first SYNC.
        deadline = time.monotonic() + self.boot_timeout
        while any(link.booted for link in master.links) and time.monotonic() < deadline:
            master.bring_up_rebooted()
        for link in missing:
            link.boot_error = ('%s: no boot-up within %g s (boot_timeout): node id, wiring, '
                               'power?' % (link.name, self.boot_timeout))
            self.get_logger().error(link.boot_error)
        if self.homed_offset.any():         # a zero known from before (the file's)
            try:
                self.set_homed_offset(self.homed_offset)
            except ParameterError as exc:
                self.get_logger().error(str(exc))
        self.judge()

    def judge(self, force: bool = False) -> None:
        """The drives' errors now (and a lost controller); a change is
        reported at once (ERROR while any)."""
        errors = self.master.errors()
        if self.lost_controller:
            errors.append('controller lost: no leg_forces for over %g s: zero torque, '
                          'drives shut down' % self.lost_after)
        if errors != self.errors or force:
            if errors:
                self.get_logger().error('torque withheld: %s' % '; '.join(errors))
            elif self.errors:
                self.get_logger().info('every drive is back: torque again')
            self.errors = errors
            self.health.fault = ('torque withheld: ' + '; '.join(errors)) if errors else ''
            self.report()
        late = self.master.late_tpdos()
        if late:        # WARN with the counts: the reading is one period late
            self.late_tpdo = '; '.join(late)
            if self.health.log_due('late TPDO'):
                self.get_logger().warning('late TPDO: %s' % self.late_tpdo)
            self.health.warning = 'late, not yet a fault (tpdo_missing_error_ms: %d SYNCs): %s' % (
                self.master.tpdo_error_cycles, self.late_tpdo)

    def serve(self, timeout: float) -> None:
        """Housekeeping, and forces for up to ``timeout`` s."""
        self.housekeeping(time.monotonic())
        self.forces_in.poll(timeout)

    def publish(self, ns: int) -> bool:
        """This cycle's readings as ``leg_lengths`` stamped ``ns``; True if complete."""
        lengths, rates = self.master.readings()
        sec, nanosec = divmod(ns, 1_000_000_000)
        self.sent_wall[ns] = time.perf_counter()
        if len(self.sent_wall) > 1000:
            self.sent_wall.pop(next(iter(self.sent_wall)))
        self.send_lengths(self.lengths_out.fill(sec, nanosec, position=lengths, velocity=rates))
        self.cycles += 1
        return all(math.isfinite(v) for v in lengths + rates)

    def report(self):
        master = self.master
        values = self.health.values
        self.wire.measure()             # planned and measured load, unknown COB-IDs
        values.update(self.wire.values())
        wire_error, wire_warning = self.wire.verdict()      # (of the last window)
        torque = ('torque withheld: ' + '; '.join(self.errors)) if self.errors else ''
        self.health.fault = '; '.join(m for m in (torque, wire_error) if m)
        if wire_warning or self.health.warning.startswith(WARNING_PREFIX):
            self.health.warning = wire_warning
        values.update({'sample': self.k, 'clock_mode': self.mode, 'missed_cycles': self.missed,
                       'force_timeouts': self.timeouts})
        for link in master.links:
            values['drive/%s' % link.leg.name] = '%s, %s, TPDOs missed %d, late %d, EMCYs %d' % (
                'up' if link.up else 'down', link.state.lower(), link.missed_tpdo,
                link.late_tpdo, link.emcys)
        if not self.started:
            return
        if self.mode == 'lockstep':
            self.health.report(ros_time(self.k * self.period), final=self.closing)
        else:
            self.health.report(final=self.closing)

    # -- the loops ---------------------------------------------------------------------------
    def run(self):
        try:
            self.bring_up()
        except NoDriveAnswers as exc:
            self.get_logger().error(str(exc))
            print('canopen_bridge: error: %s' % exc, file=sys.stderr, flush=True)
            return 1
        try:
            self.wait_for_matches(self.startup_missing)
            self.forces_in = self.start_hot_loop(self.sub_forces)
            n_samples = int(round(self.duration * self.rate)) if self.duration > 0 else None
            self.get_logger().info('%s at %g Hz%s' % (self.mode, self.rate,
                                                      ', %d samples' % n_samples if n_samples
                                                      else ''))
            if self.mode == 'lockstep':
                self.run_lockstep(n_samples)
            else:
                self.run_realtime(n_samples)
        finally:                # every way out: the end, a stop signal, an exception
            self.stop_drives()
        self.write_summary_file(self.summary())
        return 0

    def stop_drives(self) -> None:
        """Leave the drives safe (once; docs/bus.md, "Stopping")."""
        if self.stopped_drives is not None:
            return
        states = self.master.safe_stop()
        self.stopped_drives = states
        self.health.values['safe_stop'] = ', '.join('%s: %s' % (leg, state.lower())
                                                    for leg, state in states.items())
        self.get_logger().info('safe stop: zero torque, shutdown, NMT pre-operational: %s'
                               % (self.health.values['safe_stop'] or 'no drive was up'))

    def summary(self) -> dict:
        out = super().summary()
        out.update({'rate_hz': self.rate, 'clock_mode': self.mode,
                    'cycles': self.cycles, 'missed_cycles': self.missed,
                    'bus_wait_s': round(self.bus_wait_s, 3),
                    'answer_wait_s': round(self.answer_wait_s, 3),
                    'force_timeouts': self.timeouts,
                    'tpdo_missed': {link.leg.name: link.missed_tpdo
                                    for link in self.master.links},
                    'tpdo_late': {link.leg.name: link.late_tpdo for link in self.master.links},
                    'syncs_skipped': self.schedule.skipped if self.schedule else 0,
                    'drives_at_stop': self.stopped_drives,
                    'bus_load_computed_percent': {load.bus: round(load.percent, 1)
                                                  for load in self.config.loads(self.rate)}})
        return out

    def close(self):
        try:
            self.stop_drives()      # (a way out before run's own: the drives first)
        finally:
            super().close()
            self.master.close()


@quiet_on_closed_pipe
def main(argv=None):
    sys.exit(run('canopen_bridge', __doc__.split('\n\n')[0], BridgeNode, argv))


if __name__ == '__main__':
    main()
