"""The supervisor's trip logic (core/supervisor.py), in the closed loop with
the plant's dynamics and fault model, sample for sample as a lockstep rig
with ``rig --supervisor`` runs it (no DDS here; test_supervisor_dds.py runs
the node)."""
import numpy as np
import pytest

from stewart63_ros.core.params import ParameterError
from stewart63_ros.core.supervisor import (
    CAUSES,
    DESCEND,
    HOLD,
    ZERO,
    Descent,
    limits_from_params,
    rest_lengths,
    run_supervised,
    supervisor_from_params,
)

RATE = 1000.0


@pytest.fixture(scope='module')
def params(setup, mech):
    return dict(setup.to_params())


def supervised(setup, params, duration, faults=(), **overrides):
    sup = supervisor_from_params(setup, dict(params, **overrides), RATE)
    return sup, run_supervised(setup, sup, duration, RATE, list(faults))


def test_untripped_forwards_every_request_unchanged(setup, mech, params):
    sup, out = supervised(setup, params, 2.0)
    assert sup.trips == []
    np.testing.assert_array_equal(out['forces'], out['requests'])


def test_each_cause_has_one_of_the_three_safe_actions():
    assert {action for action, _ in CAUSES.values()} == {ZERO, HOLD, DESCEND}


@pytest.mark.parametrize('faults, overrides, causes, first_bad', [
    # a frozen reading: the platform leaves while the reading does not follow
    (['sensor_stuck:all@0'], {}, ('tracking_error',), 0.0),
    # a dead piston: the platform falls on that side (leg speed off: the box
    # or the tracking error catches it)
    (['actuator_dead:leg_1@0.5'], {'trip_leg_speed': 0.0}, ('pose_box', 'tracking_error'), 0.5),
    # a reading that stops coming: stale after stale_lengths_ms (20 ms)
    (['sensor_dropout:leg_2@0.5'], {}, ('lengths_stale',), 0.5),
])
def test_faults_trip_on_their_cause_with_zero_latency_the_same_every_run(setup,
        mech, params, faults, overrides, causes, first_bad):
    runs = [supervised(setup, params, 3.0, faults, **overrides)[0] for _ in range(2)]
    trip = runs[0].trip
    assert trip is not None and trip.cause in causes, runs[0].trips
    assert trip.sample_ns >= first_bad * 1e9
    # latency: the answer to the sample that crossed the limit is the safe force
    assert trip.safe_ns == trip.sample_ns
    assert (runs[1].trip.cause, runs[1].trip.sample_ns) == (trip.cause, trip.sample_ns)


def test_dropout_trips_exactly_when_the_reading_has_been_missing_for_stale_lengths_ms(setup,
        mech, params):
    sup, out = supervised(setup, params, 1.0, ['sensor_dropout:leg_2@0.5'],
                          stale_lengths_ms=20.0)
    # sample 499 is the last good one; 500..519 missing: 20 ms at 519
    assert sup.trip.sample_ns == 519_000_000
    assert np.all(out['forces'][519:] == 0.0)          # zero force from the trip on
    assert not np.all(out['forces'][518] == 0.0)


def test_a_nan_request_trips_and_holds_the_last_good_lengths(setup, mech, params):
    sup = supervisor_from_params(setup, params, RATE)
    lengths = np.array(setup.task.setpoint_lengths, float)
    sup.on_sample(0, lengths, np.zeros(6))
    assert np.all(sup.on_request(0, np.ones(6)) == 1.0)
    sup.on_sample(1_000_000, lengths + 0.01, np.zeros(6))
    forces = sup.on_request(1_000_000, np.array([1.0, np.nan, 0, 0, 0, 0]))
    assert sup.trip.cause == 'bad_command' and sup.trip.action == HOLD
    # eq. (40) towards the last good lengths (those of this sample: it was
    # good), plus what holds the platform against gravity there
    from stewart63_ros.core.laws import PDGravityLaw
    gravity = PDGravityLaw(mech, setup.to_params())
    hold = lengths + 0.01
    position, rotation, _ = gravity.estimator(hold, np.zeros(6))
    holding = gravity.holding_forces(position, rotation)
    np.testing.assert_allclose(forces, holding, atol=1e-9)
    sup.on_sample(2_000_000, lengths, np.zeros(6))
    position, rotation, _ = gravity.estimator(lengths, np.zeros(6))
    np.testing.assert_allclose(sup.safe_forces(2_000_000), np.array(setup.gains.kp) * 0.01
                               + gravity.holding_forces(position, rotation))
    # a wrong-sized request trips too
    sup2 = supervisor_from_params(setup, params, RATE)
    sup2.on_sample(0, lengths, np.zeros(6))
    sup2.on_request(0, np.ones(5))
    assert sup2.trip.cause == 'bad_command'


@pytest.mark.parametrize('trip_at', [0.05, 2.0])     # while rising fast; at rest at the setpoint
def test_the_descent_ends_at_rest_inside_the_soft_stroke(setup, mech, params, trip_at):
    """The plant's dynamics (RK4, end stops) under the descent: every true
    leg length inside the soft stroke all the way, at rest at the rest
    lengths at the end, no leg faster than the profile allows."""
    sup = supervisor_from_params(setup, params, RATE)
    limits = sup.limits

    class EstopAt:
        timed = True

        def __init__(self, controller):
            self.controller = controller

        def forces(self, t, lengths, rates):
            if abs(t - trip_at) < 0.5 / RATE:
                sup.trip_now('estop', 'test')
                return sup.safe_forces(int(round(t * 1e9)))
            return self.controller.forces(t, lengths, rates)

    from stewart63_ros.core.laws import Controller
    descent = Descent(np.full(6, 1.9), sup.rest, limits.descent_speed)   # ~ its duration
    out = run_supervised(setup, sup, trip_at + descent.duration + 1.5, RATE,
                         controller=EstopAt(Controller(setup)))
    assert sup.trip.cause == 'estop' and sup.trip.action == DESCEND
    k = int(round(trip_at * RATE))
    after = out['lengths'][k:]
    assert after.min() >= limits.soft_min and after.max() <= limits.soft_max
    speeds = np.abs(np.diff(after, axis=0)) * RATE
    assert speeds.max() <= max(1.3 * limits.descent_speed, np.abs(np.diff(
        out['lengths'][k - 1:k + 1], axis=0)).max() * RATE + 1e-3)
    final = out['states'][-1]
    np.testing.assert_allclose(out['lengths'][-1], sup.rest, atol=0.01)   # PD's sag
    assert np.abs(final[7:]).max() < 1e-3                                 # at rest
    assert out['lengths'][-1].min() > limits.soft_min


def test_the_rest_pose_is_level_inside_the_soft_stroke(setup, mech, params):
    limits = limits_from_params(mech, params)
    rest = rest_lengths(setup, limits)
    assert rest.min() == pytest.approx(limits.soft_min + limits.rest_clearance, abs=1e-9)
    assert rest.max() < limits.soft_max


def test_a_reset_is_refused_while_the_cause_holds(setup, mech, params):
    sup = supervisor_from_params(setup, params, RATE)
    good = np.array(setup.task.setpoint_lengths, float)
    bad = good.copy()
    bad[2] = sup.limits.soft_min - 0.01
    sup.on_sample(0, good, np.zeros(6))
    sup.on_request(0, np.zeros(6))
    sup.on_sample(1_000_000, bad, np.zeros(6))
    assert sup.trip.cause == 'stroke' and sup.trip.safe_ns is None
    sup.safe_forces(1_000_000)
    ok, why = sup.reset()
    assert not ok and 'leg_3' in why and 'stroke' in why
    sup.on_sample(2_000_000, good, np.zeros(6))
    ok, why = sup.reset()
    assert ok and sup.trip is None, why


def test_estop_and_reset_are_answered_before_any_sample(setup, mech, params):
    sup = supervisor_from_params(setup, params, RATE)
    sup.trip_now('estop', '~/estop')
    ok, why = sup.reset()
    assert not ok and 'NaN' in why      # no reading yet: nothing to resume on


@pytest.mark.parametrize('overrides, key', [
    ({'stroke_margin': 0.6}, 'stroke_margin'),          # no soft stroke left
    ({'stroke_margin': -0.01}, 'stroke_margin'),
    ({'trip_leg_speed': -1.0}, 'trip_leg_speed'),
    ({'descent_speed': 0.6, 'trip_leg_speed': 0.5}, 'descent_speed'),
    ({'pose_box': [0, 0, 1, 0.1, 0.1, 0.5]}, 'pose_box'),
    ({'pose_box': [0, 0, 1]}, 'pose_box'),
    ({'stale_lengths_ms': 0.0}, 'stale_lengths_ms'),
    ({'rest_clearance': 2.0}, 'rest_clearance'),
])
def test_contradictory_limits_are_refused_naming_the_key(setup, mech, params, overrides, key):
    with pytest.raises(ParameterError) as exc:
        supervisor_from_params(setup, dict(params, **overrides), RATE)
    assert exc.value.key == key


def test_homing_recovers_the_hidden_offsets_within_the_sensor_resolution(setup, mech, params):
    """Incremental sensors with unknown zeros (the plant's homing_offset),
    quantised at 0.1 mm: the homing drives every leg to its upper end stop
    (the plant's dynamics, its end-stop spring), finds each offset, sets it,
    brings the legs back; only then do the controller's forces go through."""
    from stewart63_ros.core.sensor import SensorModel
    resolution = 1e-4
    hidden = np.array([3.0, -2.0, 5.0, 0.0, -4.0, 1.2]) * 1e-3
    sup = supervisor_from_params(setup, dict(params, homing=True, homing_speed=0.2), RATE)
    out = run_supervised(setup, sup, 12.0, RATE, homing_offset=hidden,
                         sensor=SensorModel({'sensor_resolution': resolution}))
    assert sup.homed and sup.trips == []
    assert np.all(np.abs(sup.offsets - hidden) <= resolution), (sup.offsets - hidden)
    # every leg reached its stop; none of the controller's forces went through before
    assert np.all(out['lengths'].max(axis=0) > mech.leg_length_max)
    first = int(np.argmax(np.isfinite(out['requests'][:, 0])))
    assert first > 0 and np.all(np.isnan(out['requests'][:first]))
    np.testing.assert_array_equal(out['forces'][first:], out['requests'][first:])
    # once homed the readings are true (to the resolution, and the offset found)
    np.testing.assert_allclose(out['measured'][first:], out['lengths'][first:],
                               atol=1.5 * resolution)     # quantum + what homing left


def test_homing_to_stops_no_pose_reaches_is_refused(setup, mech, params):
    # the default 6-3 machine: legs 1 and 2 share a vertex over base points
    # 2.95 m apart, so they cannot both be at 1.2 m
    with pytest.raises(ParameterError) as exc:
        supervisor_from_params(setup, dict(params, homing=True, homing_direction='retract'),
                               RATE)
    assert exc.value.key == 'homing_direction' and 'legs 1 and 2' in str(exc.value)
