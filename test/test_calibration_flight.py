"""A calibration plan is flown on machines off its drawing before it is written
(core/machine/calibration_flight.py, docs/calibration.md "The plan and the machine").

The 6-6 here is one nobody tuned for it (`hexapod_b`): a small hexapod, base
joints on a 0.75 m circle 4 cm up, platform joints on a 0.32 m circle 5 cm
below its frame, 10 kg, stroke 0.65-1.05 m. Its drawing flies the plan of
seed 0 within 5 mm, while one machine 3 mm off it sags through a
singularity near the plan's ninth pose: the rule strikes that pose.
"""
from __future__ import annotations

import numpy as np
import pytest

from stewart63_ros.core.machine import calibration_flight as flight
from stewart63_ros.core.machine import calibration_plan as cp
from stewart63_ros.core.machine.supervisor import limits_from_params
from stewart63_ros.core.plumbing.params import load_setup

#: The flights' rate [Hz]: below the plant's 1 kHz for the test's time; the
#: failure and the cure are the same at 100 Hz (checked; at 50 Hz they are not).
RATE = 100.0
TOLERANCE = 0.003
#: Machines flown: half the default, for the test's time (the fourth fails).
MACHINES = 4


def hexapod_b_params() -> dict:
    """A 6-6 as a lab would write it: pairs of joints on two circles, each
    base pair's legs to two platform pairs."""
    def ring(radius, height, degrees):
        return [round(float(v), 6) for a in np.radians(degrees)
                for v in (radius * np.cos(a), radius * np.sin(a), height)]
    return {
        'base_points': ring(0.75, 0.04, [76, 104, 196, 224, 316, 344]),
        'platform_points': ring(0.32, -0.05, [52, 128, 172, 248, 292, 8]),
        'platform_mass': 10.0, 'platform_com': [0.0, 0.0, -0.02],
        'platform_inertia': [0.31, 0.31, 0.61, 0.0, 0.0, 0.0],
        'leg_lower_mass': 1.5, 'leg_upper_mass': 0.7, 'leg_lower_com': 0.25,
        'leg_upper_com': 0.25, 'leg_lower_inertia': [0.001, 0.05],
        'leg_upper_inertia': [0.0002, 0.02], 'piston_damping': 40.0, 'ujoint_damping': 0.4,
        'gravity': [0.0, 0.0, -9.81], 'kp': [4000.0] * 6, 'kv': [300.0] * 6,
        'leg_length_min': 0.65, 'leg_length_max': 1.05, 'max_force': 2000.0,
        'setpoint_lengths': [0.83, 0.83, 0.82, 0.82, 0.82, 0.82],
        'initial_position': [0.0, 0.01, 0.74], 'initial_velocity': [0.0, 0.0, 0.0],
        'initial_orientation': [0.005, -0.01, 0.02],
        'initial_orientation_rate': [0.0, 0.0, 0.0]}


@pytest.fixture(scope='module')
def hexapod_b_file(tmp_path_factory):
    import yaml
    path = tmp_path_factory.mktemp('hexapod_b') / 'hexapod_b.yaml'
    path.write_text(yaml.safe_dump({'/**': {'ros__parameters': hexapod_b_params()}}))
    return path


@pytest.fixture(scope='module')
def hexapod_b(hexapod_b_file):
    setup = load_setup(hexapod_b_file)
    assert setup.mechanism.layout == '6-6'
    return setup


def options(setup):
    limits = cp.plan_limits(setup.mechanism, limits_from_params(
        setup.mechanism, setup.to_params()))
    return ({'limits': limits},
            {'hold': 0.3, 'move': 1.0, 'leg_speed': 0.1, 'limits': limits})


def test_a_pose_a_machine_off_the_drawing_cannot_fly_is_struck(hexapod_b):
    plan_options, reference_options = options(hexapod_b)
    # A tolerance of 0 flies nothing: the plan as made on the drawing.
    assert flight.flown_plan(hexapod_b, 10, RATE, {}, plan_options, reference_options,
                             points=0.0, offsets=0.0, rounds=1).flights == []
    flown = flight.flown_plan(hexapod_b, 10, RATE, {}, plan_options, reference_options,
                              points=TOLERANCE, offsets=TOLERANCE, machines=MACHINES)
    # One machine of four sagged through a singularity (or left the bound)
    # on the way to a pose: struck, with every candidate near it.
    assert flown.struck, 'no flight failed: the test lost its case'
    print('\n' + '\n'.join(why for _, _, why in flown.struck))
    for position, rotation, _ in flown.struck:
        assert np.all(cp.pose_distance(hexapod_b.mechanism, flown.plan.positions,
                                       flown.plan.rotations, position, rotation)
                      >= cp.STRIKE_RADIUS)
    # The plan written: every machine flew it without a trip, within the bound.
    assert len(flown.flights) == MACHINES
    for one in flown.flights:
        assert one.ok and one.trip == ''
        assert one.position_max <= flight.BOUND_SHARE * flight.TRACKING_BOUND[0]
        assert one.angle_max <= flight.BOUND_SHARE * flight.TRACKING_BOUND[1]


def test_a_machine_too_far_off_to_track_anywhere_is_refused_before_a_flight(hexapod_b):
    """1.5 cm off, this small hexapod stands beyond the tracking bound at its
    start already: no plan can help, and the message says what to state."""
    plan_options, reference_options = options(hexapod_b)
    with pytest.raises(cp.PlanError, match='before any move, so no plan tracks'):
        flight.flown_plan(hexapod_b, 10, RATE, {}, plan_options, reference_options,
                          points=0.015, offsets=0.015)


def test_the_flights_bound_is_rigs_tracking_bound():
    from stewart63_ros.tools.rig import TRACKING_BOUND
    assert flight.TRACKING_BOUND == TRACKING_BOUND


def test_calibrate_plan_takes_the_tolerance_and_says_why_it_refuses(hexapod_b_file, tmp_path,
                                                                    capsys):
    """``plan --tolerance`` reaches the flights: 1.5 cm is refused (exit 2,
    one line, nothing written); a negative one is refused as an option."""
    from stewart63_ros.tools import calibrate
    out = tmp_path / 'plan'
    argv = ['plan', '--params', str(hexapod_b_file), '--poses', '10', '--out', str(out)]
    assert calibrate.main(argv + ['--tolerance', '0.015', '0.015']) == 2
    err = capsys.readouterr().err
    assert 'before any move, so no plan tracks' in err and '+-0.015 m points' in err, err
    assert not out.exists()
    assert calibrate.main(argv + ['--tolerance', '-0.001', '0.01']) == 2
    assert '--tolerance must be a number >= 0' in capsys.readouterr().err
