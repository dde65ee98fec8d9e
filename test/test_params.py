"""The parameter file: the default loads, every bad file is refused naming its key.

Bad files are the default file with one change, written to a temporary
directory. The same files are also handed to ``sim``, which must exit
non-zero and name the key on stderr (docs/interface.md, "Parameters").
"""
import copy
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from stewart63_ros.core.plumbing.params import (
    ParameterError,
    default_params_path,
    load_mechanism,
    mechanism_from_params,
    read_parameter_file,
)

SECTION = '/**'


@pytest.fixture(scope='module')
def default_doc(default_params_file):
    return yaml.safe_load(default_params_file.read_text())


def write_variant(tmp_path, doc, change=None, remove=None, name='bad.yaml'):
    doc = copy.deepcopy(doc)
    params = doc[SECTION]['ros__parameters']
    if change:
        params.update(change)
    for key in remove or ():
        del params[key]
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, default_flow_style=None))
    return path


def _replaced(values, index, new):
    values = list(values)
    values[index] = new
    return values


def _base_with(doc, i, j):
    """base_points with b_j moved onto b_i (1-based)."""
    base = np.array(doc[SECTION]['ros__parameters']['base_points'], dtype=float).reshape(6, 3)
    base[j - 1] = base[i - 1]
    return base.ravel().tolist()


# (id, change or None, keys to remove, expected key, words expected in the message)
BAD_FILES = [
    ('short-array', {'base_points': list(range(17))}, (), 'base_points', ['18']),
    ('long-array', {'kp': [4000.0] * 7}, (), 'kp', ['6']),
    ('scalar-for-array', {'platform_com': 0.0}, (), 'platform_com', ['3']),
    ('text-for-number', {'platform_mass': 'heavy'}, (), 'platform_mass', []),
    ('nan-scalar', {'platform_mass': float('nan')}, (), 'platform_mass', []),
    ('nan-in-array', {'gravity': [0.0, float('nan'), -9.81]}, (), 'gravity', []),
    ('inf-in-array', {'platform_points': _replaced([0.5, 0, 0, -0.25, 0.433013, 0, -0.25,
                                                   -0.433013, 0], 4, float('inf'))},
     (), 'platform_points', []),
    ('negative-mass', {'platform_mass': -15.0}, (), 'platform_mass', []),
    ('zero-mass', {'leg_lower_mass': 0.0}, (), 'leg_lower_mass', []),
    ('negative-leg-mass', {'leg_upper_mass': -1.5}, (), 'leg_upper_mass', []),
    ('inertia-not-pd', {'platform_inertia': [1.0, 1.0, 1.5, 1.2, 0.0, 0.0]}, (),
     'platform_inertia', ['positive definite']),
    ('inertia-negative-diagonal', {'platform_inertia': [-0.95, 0.95, 1.875, 0, 0, 0]}, (),
     'platform_inertia', []),
    ('inertia-triangle', {'platform_inertia': [0.2, 0.3, 1.875, 0.0, 0.0, 0.0]}, (),
     'platform_inertia', ['triangle']),
    ('leg-inertia-axial-too-big', {'leg_lower_inertia': [0.5, 0.2]}, (), 'leg_lower_inertia',
     ['triangle']),
    ('piston-inertia-axial-too-big', {'leg_upper_inertia': [0.13, 0.06]}, (),
     'leg_upper_inertia', ['triangle']),
    ('lmax-below-lmin', {'leg_length_min': 1.2, 'leg_length_max': 1.1}, (), 'leg_length_max',
     ['leg_length_min']),
    ('lmax-equals-lmin', {'leg_length_min': 1.5, 'leg_length_max': 1.5}, (), 'leg_length_max',
     ['leg_length_min']),
    ('missing-mass', None, ('platform_mass',), 'platform_mass', ['missing']),
    ('missing-base', None, ('base_points',), 'base_points', ['missing']),
    ('missing-gains', None, ('kv',), 'kv', ['missing']),
    ('negative-endstop', {'endstop_stiffness': -1.0}, (), 'endstop_stiffness', ['>= 0']),
    ('nan-endstop', {'endstop_damping': float('nan')}, (), 'endstop_damping', []),
    ('text-endstop', {'endstop_damping': 'soft'}, (), 'endstop_damping', ['number']),
]


@pytest.mark.parametrize('case', BAD_FILES, ids=[c[0] for c in BAD_FILES])
def test_bad_file_names_its_key(tmp_path, default_doc, case):
    _, change, remove, key, words = case
    path = write_variant(tmp_path, default_doc, change, remove)
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == key
    assert str(info.value).startswith(key + ':')
    for word in words:
        assert word in str(info.value)


def test_nan_written_as_yaml_nan(tmp_path, default_params_file):
    """The YAML spelling ``.nan`` (and ``.inf``), edited into the text itself."""
    text = default_params_file.read_text()
    pattern = re.compile(r'^(\s*platform_mass:)[^#\n]*', re.MULTILINE)
    assert len(pattern.findall(text)) == 1
    for spelled in ('.nan', '.NaN', '.inf', '-.inf'):
        path = tmp_path / 'nan.yaml'
        path.write_text(pattern.sub(r'\1 %s ' % spelled, text))
        with pytest.raises(ParameterError) as info:
            load_mechanism(path)
        assert info.value.key == 'platform_mass'


def test_coincident_base_points(tmp_path, default_doc):
    path = write_variant(tmp_path, default_doc, {'base_points': _base_with(default_doc, 1, 3)})
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'base_points'
    assert 'b_1' in str(info.value) and 'b_3' in str(info.value)


def test_pair_with_coincident_base_points(tmp_path, default_doc):
    path = write_variant(tmp_path, default_doc, {'base_points': _base_with(default_doc, 3, 4)})
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'base_points'
    assert 'pair' in str(info.value) and 'b_3' in str(info.value) and 'b_4' in str(info.value)


def test_collinear_platform_points(tmp_path, default_doc):
    # p_3 on the line through p_1 and p_2
    points = [0.5, 0.0, 0.0, -0.25, 0.433013, 0.0, -1.0, 0.866026, 0.0]
    path = write_variant(tmp_path, default_doc, {'platform_points': points})
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'platform_points'
    assert 'collinear' in str(info.value)


def test_coincident_platform_points(tmp_path, default_doc):
    points = [0.5, 0.0, 0.0, 0.5, 0.0, 0.0, -0.25, -0.433013, 0.0]
    path = write_variant(tmp_path, default_doc, {'platform_points': points})
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'platform_points'


def _initial_lengths(doc):
    """Leg lengths of the file's initial pose, computed here (eqs. 2-5)."""
    raw = doc[SECTION]['ros__parameters']
    rot = Rotation.from_euler('xyz', raw['initial_orientation']).as_matrix()
    plat = np.reshape(raw['platform_points'], (3, 3))[[0, 0, 1, 1, 2, 2]]
    legs = np.asarray(raw['initial_position']) + plat @ rot.T - np.reshape(raw['base_points'],
                                                                            (6, 3))
    return np.linalg.norm(legs, axis=1)


@pytest.mark.parametrize('limit', ['leg_length_max', 'leg_length_min'])
def test_stroke_that_cannot_hold_the_initial_pose(tmp_path, default_doc, limit):
    lengths = _initial_lengths(default_doc)
    if limit == 'leg_length_max':   # the longest initial leg sticks out
        change = {'leg_length_min': 0.5, 'leg_length_max': float(lengths.max()) - 0.01}
    else:                           # the shortest initial leg is too short
        change = {'leg_length_min': float(lengths.min()) + 0.01, 'leg_length_max': 5.0}
    path = write_variant(tmp_path, default_doc, change)
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'initial_position'
    assert limit in str(info.value)
    # it names a leg that really is outside
    outside = np.flatnonzero((lengths < change['leg_length_min'])
                             | (lengths > change['leg_length_max']))
    named = re.search(r'leg_(\d)', str(info.value).split(':', 1)[1])
    assert named and int(named.group(1)) - 1 in outside


def test_setpoint_outside_stroke(tmp_path, default_doc):
    path = write_variant(tmp_path, default_doc,
                         {'setpoint_lengths': [1.9, 1.9, 1.6, 1.6, 1.6, 2.5]})
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == 'setpoint_lengths'
    assert 'leg_6' in str(info.value)


# -- files that are not parameter files -------------------------------------------------------
NOT_PARAMETER_FILES = [
    ('not-yaml', 'base_points: [1.0, 2.0\nplatform_mass: {15\n', 'params file', 'YAML'),
    ('yaml-list', '- 1\n- 2\n', 'params file', 'ros__parameters'),
    ('plain-mapping', 'platform_mass: 15.0\n', 'params file', 'ros__parameters'),
    ('no-wildcard-section', 'other_node:\n  ros__parameters:\n    platform_mass: 15.0\n',
     'params file', 'ros__parameters'),
    ('empty', '', 'params file', 'ros__parameters'),
]


@pytest.mark.parametrize('case', NOT_PARAMETER_FILES, ids=[c[0] for c in NOT_PARAMETER_FILES])
def test_not_a_parameter_file(tmp_path, case):
    _, text, key, word = case
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(ParameterError) as info:
        load_mechanism(path)
    assert info.value.key == key
    assert word in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ParameterError) as info:
        load_mechanism(tmp_path / 'nowhere.yaml')
    assert info.value.key == 'params file'
    assert 'nowhere.yaml' in str(info.value)


# -- the default file -----------------------------------------------------------------------------
def test_default_file_loads(setup, default_params_file, default_doc):
    mech = load_mechanism(default_params_file)
    raw = default_doc[SECTION]['ros__parameters']
    np.testing.assert_array_equal(mech.base_points, np.reshape(raw['base_points'], (6, 3)))
    np.testing.assert_array_equal(mech.platform_points, np.reshape(raw['platform_points'], (3, 3)))
    assert mech.platform_mass == raw['platform_mass']
    ixx, iyy, izz, ixy, ixz, iyz = raw['platform_inertia']
    np.testing.assert_array_equal(mech.platform_inertia,
                                  [[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    np.testing.assert_array_equal(mech.gravity, raw['gravity'])
    np.testing.assert_array_equal(setup.task.setpoint_lengths, raw['setpoint_lengths'])
    assert mech.leg_length_min < mech.leg_length_max
    # the packaged default is this file, and arrays are frozen
    assert default_params_path().resolve() == default_params_file.resolve()
    with pytest.raises(ValueError):
        mech.base_points[0, 0] = 1.0


def test_node_section_overrides_wildcard(default_params_file):
    shared = read_parameter_file(default_params_file)
    plant = read_parameter_file(default_params_file, node_name='plant')
    assert 'sensor_rate' not in shared
    assert plant['sensor_rate'] == 1000.0
    assert plant['platform_mass'] == shared['platform_mass']


def test_off_diagonal_inertia_convention(default_mech):
    """platform_inertia lists matrix elements (Ixy = -sum m x y), not products of inertia."""
    mech = default_mech.replace(platform_inertia=[1.0, 1.2, 1.5, -0.1, 0.05, 0.02])
    np.testing.assert_array_equal(mech.platform_inertia,
                                  [[1.0, -0.1, 0.05], [-0.1, 1.2, 0.02], [0.05, 0.02, 1.5]])


def test_replace_validates(default_setup, default_mech):
    with pytest.raises(ParameterError) as info:
        default_mech.replace(platform_mass=0.0)
    assert info.value.key == 'platform_mass'
    params = default_setup.to_params()
    params['leg_lower_inertia'] = [1.0, 0.1]
    with pytest.raises(ParameterError) as info:
        mechanism_from_params(params)
    assert info.value.key == 'leg_lower_inertia'


# -- the sim command on bad files ----------------------------------------------------------------
SIM_CASES = [
    ('short-array', {'base_points': list(range(17))}, (), 'base_points'),
    ('nan', {'gravity': [0.0, float('nan'), -9.81]}, (), 'gravity'),
    ('inertia-triangle', {'platform_inertia': [0.2, 0.3, 1.875, 0.0, 0.0, 0.0]}, (),
     'platform_inertia'),
    ('missing-key', None, ('platform_mass',), 'platform_mass'),
]


def _run_sim(params, out):
    return subprocess.run(
        [sys.executable, '-m', 'stewart63_ros.tools.sim', '--params', str(params),
         '--duration', '0.1', '--out', str(out)],
        capture_output=True, text=True, timeout=120)


@pytest.mark.slow      # a sim process per case
@pytest.mark.parametrize('case', SIM_CASES, ids=[c[0] for c in SIM_CASES])
def test_sim_refuses_bad_file(tmp_path, default_doc, case):
    _, change, remove, key = case
    path = write_variant(tmp_path, default_doc, change, remove)
    result = _run_sim(path, tmp_path / 'out')
    assert result.returncode != 0
    assert key in result.stderr
    assert 'Traceback' not in result.stderr, 'a bad file deserves a message, not a traceback'
    assert not (tmp_path / 'out' / 'trajectory.csv').exists()


@pytest.mark.slow
def test_sim_refuses_non_yaml(tmp_path):
    path = tmp_path / 'bad.yaml'
    path.write_text('base_points: [1.0, 2.0\n')
    result = _run_sim(path, tmp_path / 'out')
    assert result.returncode != 0
    assert 'params file' in result.stderr
    assert 'Traceback' not in result.stderr


def test_one_splitter_for_the_ros_arguments():
    """record, play and the nodes' parameters split --ros-args the same way:
    every group up to its ``--``, a value taken whole even when it starts with '-'."""
    from stewart63_ros.runtime.parameters import ros_arguments
    from stewart63_ros.runtime.ros_args import rclpy_args, split_ros_args
    line = ['bag', '--rate', '2', '--ros-args', '-r', '__ns:=/rig2', '-p', 'x:=--', '--',
            '--loop', '--ros-args', '--params-file', 'f.yaml']
    own, ros = split_ros_args(line)
    assert own == ['bag', '--rate', '2', '--loop']
    assert ros == ['--ros-args', '-r', '__ns:=/rig2', '-p', 'x:=--', '--ros-args',
                   '--params-file', 'f.yaml']
    assert rclpy_args('play', ros) == ['play'] + ros
    assert split_ros_args(['bag']) == (['bag'], []) and rclpy_args('play', []) is None
    args = ros_arguments(['plant'] + line)
    assert args.params_files == ['f.yaml'] and args.overrides == [(None, 'x', '--')]
