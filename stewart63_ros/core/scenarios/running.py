"""Running a scenario in this process: the plant, the controller and the
supervisor it names, built from its parameters, and ``run_sim`` (the sampled
loop of ``simulate.run_sampled`` at the plant's ``sensor_rate``, the loop the
lockstep rig closes over DDS sample for sample). Running on the rig is the
``scenario`` tool's (``RigRunner``).
"""
from __future__ import annotations

import functools
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from stewart63_ros.core.machine.faults import FaultModel, parse_faults
from stewart63_ros.core.plumbing.errors import ParameterError
from stewart63_ros.core.plumbing.node_parameters import read as read_declared
from stewart63_ros.core.scenarios.scenario import (
    Scenario,
    ScenarioError,
    Trace,
    TripRecord,
    WrenchInterval,
)


@functools.lru_cache(maxsize=32)
def _file_section(path: str, node: str, mtime_ns: int) -> Mapping[str, Any]:
    """A node's parameters of a file, read once per version of the file (YAML
    parsing would otherwise cost more than a 10 s run)."""
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import read_parameter_file
    return read_parameter_file(path, node)


def node_parameters(scenario: Scenario, node: str) -> dict:
    """The parameters a node of the scenario reads: its file's, then the overrides.

    Args:
        scenario: the scenario.
        node: 'plant' or 'controller'.

    Returns:
        {key: value}.

    Raises:
        ScenarioError: the parameter file cannot be read.
    """
    try:
        params = dict(_file_section(scenario.params_file, node,
                                    os.stat(scenario.params_file).st_mtime_ns))
    except OSError as exc:
        raise ScenarioError('params_file: cannot read %s (%s)'
                            % (scenario.params_file, exc.strerror)) from None
    except ParameterError as exc:
        raise ScenarioError('params_file: %s' % exc) from None
    params.update(scenario.params)
    if scenario.control_law is not None:
        params['control_law'] = scenario.control_law
    return params


def build_plant(scenario: Scenario) -> Any:
    """The plant's setup of the scenario (its machine, initial state, settings).

    Args:
        scenario: the scenario.

    Returns:
        The ``Setup``.

    Raises:
        ScenarioError: a parameter value the validation refuses (its key named).
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import setup_from_params
    try:
        return setup_from_params(node_parameters(scenario, 'plant'))
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None


def build_controller(scenario: Scenario) -> tuple[Any, Any]:
    """(controller, reference) of the scenario: a ``laws.Controller`` with its law
    and reference (None: the setpoint).

    Args:
        scenario: the scenario.

    Returns:
        (``Controller``, ``Reference`` or None).

    Raises:
        ScenarioError: the law cannot be built, the reference is refused.
    """
    # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
    from stewart63_ros.core.controllers.laws import Controller
    from stewart63_ros.core.controllers.reference import ReferenceError
    from stewart63_ros.core.controllers.reference_files import load_reference
    from stewart63_ros.core.plumbing.params import setup_from_params
    params = node_parameters(scenario, 'controller')
    try:
        setup = setup_from_params(params)
        reference = None
        if scenario.reference is not None:
            limits = (read_declared(params, 'max_leg_speed'),
                      read_declared(params, 'max_leg_acceleration'))
            if os.path.isdir(scenario.reference):
                # a topic file: read with the package's bag I/O (rosbags, no ROS)
                # lazy: bagio costs 197 ms; only a reference from a bag needs it
                from stewart63_ros.bagruns import reference_from_bag
                reference = reference_from_bag(setup.mechanism, scenario.reference, *limits)
            else:
                reference = load_reference(setup.mechanism, scenario.reference, *limits)
        return Controller(setup, params, reference=reference), reference
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None
    except ReferenceError as exc:
        raise ScenarioError('reference: %s' % exc) from None


def wrench_samples(wrench: Sequence[WrenchInterval], times: np.ndarray) -> np.ndarray | None:
    """The wrench held over each sample period (None: no wrench at all).

    Args:
        wrench: the schedule; times: (N,) the sample times [s].

    Returns:
        (N, 6) [N, N m] (platform frame), or None for an empty schedule.
    """
    if not wrench:
        return None
    out = np.zeros((len(times), 6))
    for w in wrench:
        inside = (times >= w.t_from - 1e-9) & (times < w.t_to - 1e-9)
        out[inside, :3] = w.force
        out[inside, 3:] = w.torque
    return out


class _Withholding:
    """A controller that, like the controller node, answers nothing when its
    law raises: the previous forces hold, and the sample is marked. It has
    the ``laws.Controller`` interface ``simulate`` drives (no fast path)."""

    def __init__(self, controller: Any, rate: float) -> None:
        self.controller = controller
        self.rate = rate
        self.held = np.zeros(6)
        self.withheld: list[int] = []

    def pd_gains(self) -> None:
        """No compiled fast path: every sample goes through ``forces``."""
        return None

    def forces(self, t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The law's forces, or the previous ones when the law raises."""
        # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
        from stewart63_ros.core.controllers.laws import LawError
        try:
            self.held = self.controller.forces(t, lengths, rates)
        except LawError:
            self.withheld.append(int(round(t * self.rate)))
        return self.held


def run_sim(scenario: Scenario) -> Trace:
    """Run a scenario in this process: ``run_sampled`` at the plant's
    ``sensor_rate`` (the lockstep rig's loop), faults as the plant injects them
    (seed ``sensor_seed``), the wrench schedule held per sample; a law that
    raises has its sample withheld (the previous forces hold), as the
    controller node does.

    Args:
        scenario: a scenario (any ``run``: this is how ``sim`` runs it).

    Returns:
        The run's ``Trace``.

    Raises:
        ScenarioError: the parameters, law or reference are refused.
        RuntimeError: the simulation diverged (non-finite state).
    """
    # lazy: the core's kernels cost 692 ms (numba); scenario --help, pytest
    from stewart63_ros.core.controllers.laws import PDLaw
    from stewart63_ros.core.controllers.simulate import run_sampled
    from stewart63_ros.core.mechanics.dynamics import Dynamics
    plant = build_plant(scenario)
    mech = plant.mechanism
    controller, reference = build_controller(scenario)
    rate = float(plant.setting('sensor_rate'))
    n = int(round(scenario.duration * rate))
    times = np.arange(n + 1) / rate
    wrenches = wrench_samples(scenario.wrench, times)
    faults = None
    plant_faults = list(plant.settings.get('faults') or []) + list(scenario.faults)
    if plant_faults:
        faults = FaultModel(parse_faults(plant_faults), rate, plant.setting('sensor_seed'))
    dyn = Dynamics(mech)
    if scenario.supervised:
        return _run_supervised(scenario, plant, dyn, controller, reference, rate, faults, wrenches)
    if reference is None and type(controller.law) is PDLaw and faults is None:
        # eq. (40) towards the setpoint: the compiled loop (controller.pd_gains())
        law: Any = controller
    else:
        law = _Withholding(controller, rate)
    result = run_sampled(plant, scenario.duration, rate, controller=law, dyn=dyn,
                         faults=faults, wrench=wrenches)
    if not np.all(np.isfinite(result.states)):
        raise RuntimeError('the simulation diverged (non-finite state)')
    # lazy: core.analysis.sweep costs 692 ms (numba, scipy.optimize)
    from stewart63_ros.core.analysis.sweep import leg_lengths_of_states
    lengths = leg_lengths_of_states(dyn.base_points, dyn.leg_points, result.states)
    withheld = np.zeros(len(times), bool)
    if isinstance(law, _Withholding):
        withheld[[k for k in law.withheld if k < len(times)]] = True
    return Trace(times, lengths, reference_lengths(scenario, reference, times),
                 result.forces, withheld, (mech.leg_length_min, mech.leg_length_max), rate=rate)


class _LawCalls:
    """The controller, noting the samples on which its law raised (the
    supervisor trips on them: ``run_supervised``)."""

    def __init__(self, controller: Any, rate: float) -> None:
        self.controller = controller
        self.rate = rate
        self.raised: list[int] = []

    def forces(self, t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        """The law's forces; a LawError noted, then passed on."""
        # lazy: core.controllers.laws costs 926 ms (numba); scenario --help, pytest
        from stewart63_ros.core.controllers.laws import LawError
        try:
            return self.controller.forces(t, lengths, rates)
        except LawError:
            self.raised.append(int(round(t * self.rate)))
            raise


def build_supervisor(scenario: Scenario, reference: Any = None) -> Any:
    """The supervisor of a scenario that expects a trip (or none): the
    ``supervisor`` node's parameters (the file's, then the overrides), the
    reference the controller follows (None: its setpoint).

    Args:
        scenario: the scenario.
        reference: the controller's ``Reference`` (a CSV's or a topic file's), or None.

    Returns:
        A fresh ``core.machine.supervisor.Supervisor`` at the plant's ``sensor_rate``.

    Raises:
        ScenarioError: a limit out of range or contradicting another (its key named).
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.machine.supervisor import supervisor_from_params
    from stewart63_ros.core.plumbing.params import setup_from_params
    params = node_parameters(scenario, 'supervisor')
    params['reference_file'] = ''       # the scenario's reference is handed over below
    rate = float(read_declared(node_parameters(scenario, 'plant'), 'sensor_rate'))
    try:
        supervisor = supervisor_from_params(setup_from_params(params), params, rate)
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None
    if reference is not None:
        supervisor.reference = reference
    return supervisor


def _run_supervised(scenario: Scenario, plant: Any, dyn: Any, controller: Any, reference: Any,
                    rate: float, faults: Any, wrenches: np.ndarray | None) -> Trace:
    """``run_sim`` with the supervisor between controller and plant:
    ``core.machine.supervisor.run_supervised``, the loop ``rig --supervisor`` runs."""
    # lazy: core.machine.supervisor costs 1050 ms (numba); scenario --help, pytest
    from stewart63_ros.core.machine.supervisor import run_supervised
    supervisor = build_supervisor(scenario, reference)
    law = _LawCalls(controller, rate)
    mech = plant.mechanism
    out = run_supervised(plant, supervisor, scenario.duration, rate, faults=faults,
                         controller=law, wrench=wrenches)
    if not np.all(np.isfinite(out['states'])):
        raise RuntimeError('the simulation diverged (non-finite state)')
    times = np.arange(len(out['lengths'])) / rate
    withheld = np.zeros(len(times), bool)
    withheld[[k for k in law.raised if k < len(times)]] = True

    def index(ns: int) -> int:
        return int(round(ns * 1e-9 * rate))
    trips = tuple(TripRecord(t.cause, index(t.sample_ns),
                             None if t.safe_ns is None else index(t.safe_ns) - index(t.sample_ns),
                             t.detail) for t in supervisor.trips)
    return Trace(times, out['lengths'], reference_lengths(scenario, reference, times),
                 out['forces'], withheld, (mech.leg_length_min, mech.leg_length_max),
                 rate=rate, trips=trips)


def build_controller_setup(scenario: Scenario) -> Any:
    """The controller's setup (its setpoint and gains) of the scenario.

    Args:
        scenario: the scenario.

    Returns:
        The ``Setup`` from the controller's parameters.

    Raises:
        ScenarioError: a parameter value the validation refuses.
    """
    # lazy: core.plumbing.params costs 715 ms (numba); scenario --help, pytest
    from stewart63_ros.core.plumbing.params import setup_from_params
    try:
        return setup_from_params(node_parameters(scenario, 'controller'))
    except ParameterError as exc:
        raise ScenarioError('params: %s' % exc) from None


def reference_lengths(scenario: Scenario, reference: Any, times: np.ndarray) -> np.ndarray:
    """The reference's leg lengths at ``times`` (the controller's setpoint
    without a reference).

    Args:
        scenario: the scenario; reference: its ``Reference`` or None.
        times: (N,) [s] from the run's first sample.

    Returns:
        (N, 6) [m].
    """
    if reference is None:
        setup = build_controller_setup(scenario)
        return np.tile(np.asarray(setup.task.setpoint_lengths, float), (len(times), 1))
    # lazy: core.controllers.reference costs 570 ms (numba)
    from stewart63_ros.core.controllers.reference import R_LEN
    return reference.sample_many(times)[:, R_LEN]




#: A function that runs a scenario on the rig and returns its ``Trace``
#: (the ``scenario`` tool provides it; the core knows no DDS).
RigRunner = Callable[[Scenario, str], Trace]
