"""What the platform looks like: shapes for RViz2, Foxglove, the web view and plots.

Pure numpy, no ROS. ``Scene(mech).shapes(...)`` turns one state of the rig
(pose, measured leg lengths, piston forces, setpoint pose) into a list of
``Shape``: the base plate and its six U-joints, the platform plate and its
joints (a 6-3: a triangle and its three vertices; a 6-6: the hexagon of its
six joints, ``Scene.plate_faces``), each leg as a cylinder (on the U-joint) plus a piston rod
(to the platform), a status sphere per leg (end stop, force saturation) and
the setpoint pose as a translucent ghost. ``nodes/markers.py`` turns them
into ``visualization_msgs/MarkerArray``, the ``view`` page and
``plot --animate`` draw the same shapes.

Leg geometry (eqs. 1, 2, 4): the leg direction is s_i = S_i / |S_i| with
S_i = t + R p_k - b_i from the pose (p_k the joint of leg i:
``Mechanism.leg_vertex``); each leg is drawn from b_i along s_i to
b_i + L_i s_i, L_i the *measured* length. With the pose from forward
kinematics of the same lengths the tip is the platform joint; a
difference between the two (a pose from elsewhere) shows as a gap.

Colours: a leg's piston is grey at zero force, red as the force pushes
(extends, positive) and blue as it pulls, at full colour at ``max_force``.
Its status sphere, at the cylinder's mouth, is yellow at an end stop
(L_i at or beyond a stroke limit), magenta at force saturation
(|F_i| >= max_force), and hidden (fully transparent) otherwise.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from stewart63_ros.core.mechanics.mechanism import Mechanism

#: Marker kinds (the visualization_msgs names): CYLINDER / SPHERE are one
#: shape at ``position``/``orientation``; the LIST kinds take ``points``.
CYLINDER, SPHERE, SPHERE_LIST, TRIANGLE_LIST, LINE_LIST = (
    'cylinder', 'sphere', 'sphere_list', 'triangle_list', 'line_list')

GREY = (0.62, 0.62, 0.62)
PUSH = (0.86, 0.13, 0.10)       # positive force: the piston extends
PULL = (0.12, 0.35, 0.90)       # negative force: the piston retracts
ENDSTOP = (1.0, 0.85, 0.0, 1.0)
SATURATED = (0.9, 0.0, 0.9, 1.0)
HIDDEN = (0.0, 0.0, 0.0, 0.0)


@dataclasses.dataclass
class Shape:
    """One marker. ``points`` (N, 3) for the list kinds and, for a cylinder,
    its two end centres (``position``/``orientation`` are derived from them)."""

    ns: str
    id: int
    kind: str
    color: tuple                        # r, g, b, a in [0, 1]
    scale: tuple = (1.0, 1.0, 1.0)      # as visualization_msgs/Marker.scale
    position: np.ndarray = None
    orientation: np.ndarray = None      # quaternion (x, y, z, w)
    points: np.ndarray = None


def quaternion_z_to(direction: ArrayLike) -> np.ndarray:
    """Unit quaternion (x, y, z, w) turning the z axis onto ``direction``
    (the axis of a visualization_msgs CYLINDER is its local z).

    Args:
        direction: (3,), any non-zero length.

    Returns:
        (4,) the quaternion (x, y, z, w).
    """
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    w = 1.0 + d[2]
    if w < 1e-9:                        # pointing down: half a turn about x
        return np.array([1.0, 0.0, 0.0, 0.0])
    q = np.array([-d[1], d[0], 0.0, w])
    return q / np.linalg.norm(q)


def _quaternions_z_to(directions) -> np.ndarray:
    """``quaternion_z_to`` for (N, 3) unit vectors (none pointing straight down)."""
    d = np.asarray(directions, dtype=float)
    q = np.column_stack([-d[:, 1], d[:, 0], np.zeros(len(d)), 1.0 + d[:, 2]])
    return q / np.linalg.norm(q, axis=1)[:, None]


def force_color(force: float | None, max_force: float) -> tuple:
    """Grey at 0, towards PUSH (F > 0) or PULL (F < 0), full at |F| = max_force.

    Args:
        force: F [N], or None / NaN for unknown (grey).
        max_force: the saturation [N].

    Returns:
        (r, g, b, a) in [0, 1].
    """
    if force is None or not np.isfinite(force):
        return GREY + (1.0,)
    a = min(abs(force) / max_force, 1.0)
    target = PUSH if force > 0 else PULL
    return tuple(g + a * (c - g) for g, c in zip(GREY, target)) + (1.0,)


def leg_status(length: float | None, force: float | None, mech: Mechanism) -> str:
    """What a leg's status sphere shows.

    Args:
        length: L [m] or None (unknown); force: F [N] or None (unknown).
        mech: the mechanism (stroke limits, ``max_force``).

    Returns:
        ``'endstop'`` (at or beyond a stroke limit), ``'saturated'``
        (|F| = max_force) or ``''``.
    """
    if length is not None and not mech.leg_length_min < length < mech.leg_length_max:
        return 'endstop'
    if force is not None and abs(force) >= mech.max_force * (1.0 - 1e-9):
        return 'saturated'
    return ''


class Scene:
    """The shapes of one mechanism; sizes follow its geometry.

    Args:
        mech: the mechanism.
    """

    def __init__(self, mech: Mechanism) -> None:
        self.mech = mech
        base = np.asarray(mech.base_points, dtype=float)
        plat = np.asarray(mech.platform_points, dtype=float)
        self.base_radius = float(np.max(np.linalg.norm(base[:, :2], axis=1)))
        self.platform_radius = float(np.max(np.linalg.norm(plat, axis=1)))
        span = max(self.base_radius, 0.2)
        #: cylinder (outer) and piston rod diameters, joint sphere size [m]
        self.cylinder_d = 0.045 * span
        self.rod_d = 0.022 * span
        self.joint_d = 0.06 * span
        #: the cylinder body: fits inside the shortest leg, the rod spans
        #: the rest of the longest with an overlap kept inside the body.
        self.body = 0.55 * mech.leg_length_min
        self.rod = mech.leg_length_max - 0.5 * self.body
        #: the plate's triangles, rows of indices into ``platform_points``
        self.plate_faces = plate_faces(plat)
        self._leg_joint = np.asarray(mech.leg_vertex)

    # ------------------------------------------------------------- geometry
    def vertices(self, position: ArrayLike, rot: ArrayLike) -> np.ndarray:
        """The platform's joints t + R p_k, base frame (eq. 1): a 6-3's three
        vertices, a 6-6's six joints.

        Args:
            position: t (3,) [m]; rot: R (3, 3).

        Returns:
            (3, 3) or (6, 3), one joint per row [m].
        """
        return np.asarray(position, dtype=float) + np.asarray(self.mech.platform_points) @ \
            np.asarray(rot, dtype=float).T

    def legs(self, position: ArrayLike, rot: ArrayLike,
             lengths: ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the legs are drawn.

        Args:
            position: t (3,) [m]; rot: R (3, 3).
            lengths: measured L (6,) [m]; None: the pose's own.

        Returns:
            (b (6, 3) U-joints, s (6, 3) unit leg directions from the pose
            (eq. 4), tips b_i + L_i s_i (6, 3)) [m].
        """
        mech = self.mech
        base = np.asarray(mech.base_points, dtype=float)
        verts = self.vertices(position, rot)[self._leg_joint]
        S = verts - base                                    # eq. (2)
        L_pose = np.linalg.norm(S, axis=1)
        s = S / L_pose[:, None]
        L = L_pose if lengths is None else np.asarray(lengths, dtype=float)
        return base, s, base + L[:, None] * s

    # --------------------------------------------------------------- shapes
    def shapes(self, position: ArrayLike, rot: ArrayLike, lengths: ArrayLike | None = None,
               forces: ArrayLike | None = None,
               ghost: tuple[ArrayLike, ArrayLike] | None = None) -> list[Shape]:
        """Every shape for one state.

        Args:
            position: t (3,) [m]; rot: R (3, 3): the platform pose, base frame.
            lengths: measured L (6,) [m]; None: from the pose.
            forces: F (6,) [N]; None: unknown (grey).
            ghost: (position (3,), rot (3, 3)) of the setpoint pose; None: hidden.

        Returns:
            The 24 shapes, in marker order (docs/interface.md, Markers).
        """
        mech = self.mech
        out = []
        base, s, tip = self.legs(position, rot, lengths)
        # base plate: a thin disk just under z = 0
        out.append(Shape('base', 0, CYLINDER, (0.35, 0.37, 0.40, 1.0),
                         (2.2 * self.base_radius, 2.2 * self.base_radius, 0.02),
                         position=np.array([0.0, 0.0, -0.012]),
                         orientation=np.array([0.0, 0.0, 0.0, 1.0])))
        out.append(Shape('ujoints', 0, SPHERE_LIST, (0.15, 0.15, 0.15, 1.0),
                         (self.joint_d,) * 3, points=base.copy()))
        verts = self.vertices(position, rot)
        out.append(Shape('platform', 0, TRIANGLE_LIST, (0.20, 0.65, 0.35, 1.0),
                         points=self._two_sided(verts)))
        out.append(Shape('platform_joints', 0, SPHERE_LIST, (0.1, 0.3, 0.15, 1.0),
                         (self.joint_d,) * 3, points=verts))
        lengths_v = None if lengths is None else np.asarray(lengths, dtype=float)
        forces_v = None if forces is None else np.asarray(forces, dtype=float)
        for i in range(6):
            L_i = float(np.linalg.norm(tip[i] - base[i]))
            body_end = base[i] + min(self.body, L_i) * s[i]
            out.append(_cylinder('cylinder', i, base[i], body_end, self.cylinder_d,
                                 (0.30, 0.30, 0.34, 1.0)))
            rod_start = base[i] + max(L_i - self.rod, 0.0) * s[i]
            f = None if forces_v is None else float(forces_v[i])
            out.append(_cylinder('piston', i, rod_start, tip[i], self.rod_d,
                                 force_color(f, mech.max_force)))
            status = leg_status(None if lengths_v is None else L_i, f, mech)
            color = {'endstop': ENDSTOP, 'saturated': SATURATED}.get(status, HIDDEN)
            out.append(Shape('leg_status', i, SPHERE, color, (1.6 * self.cylinder_d,) * 3,
                             position=body_end, orientation=np.array([0.0, 0.0, 0.0, 1.0])))
        out.extend(self.ghost_shapes(ghost))
        return out

    def flat(self, position: ArrayLike, rot: ArrayLike, lengths: ArrayLike | None = None,
             forces: ArrayLike | None = None,
             ghost: tuple[ArrayLike, ArrayLike] | None = None,
             ) -> tuple[np.ndarray, np.ndarray]:
        """``flatten(self.shapes(...))``, vectorized: what a 30 Hz marker
        timer can afford in a process that also serves a 1 kHz loop.

        Args:
            As ``shapes``; ``ghost`` is compared by identity (flattened again
            only when another object is passed).

        Returns:
            (float64 numbers, float32 colours), as ``flatten``.
        """
        f8, f4 = self._flat_static()
        mech = self.mech
        base, s, tip = self.legs(position, rot, lengths)
        verts = self.vertices(position, rot)
        o = self._offsets
        plate = self._two_sided(verts).ravel()
        f8[o['platform']:o['platform'] + plate.size] = plate
        f8[o['platform_joints']:o['platform_joints'] + verts.size] = verts.ravel()
        L = np.linalg.norm(tip - base, axis=1)
        body_end = base + np.minimum(self.body, L)[:, None] * s
        rod_start = base + np.maximum(L - self.rod, 0.0)[:, None] * s
        quat = _quaternions_z_to(s)
        leg = f8[o['legs']:o['legs'] + 6 * 30].reshape(6, 30)
        leg[:, 0:3] = 0.5 * (base + body_end)
        leg[:, 3:7] = quat
        leg[:, 9] = np.maximum(np.linalg.norm(body_end - base, axis=1), 1e-6)
        leg[:, 10:13] = 0.5 * (rod_start + tip)
        leg[:, 13:17] = quat
        leg[:, 19] = np.maximum(np.linalg.norm(tip - rod_start, axis=1), 1e-6)
        leg[:, 20:23] = body_end
        colors = f4[16:16 + 6 * 12].reshape(6, 12)
        if forces is None:
            colors[:, 4:8] = GREY + (1.0,)
            force = np.full(6, np.nan)
        else:
            force = np.asarray(forces, dtype=float)
            a = np.minimum(np.abs(force) / mech.max_force, 1.0)
            target = np.where((force > 0)[:, None], PUSH, PULL)
            colors[:, 4:7] = np.asarray(GREY) + a[:, None] * (target - np.asarray(GREY))
            colors[:, 7] = 1.0
            bad = ~np.isfinite(force)
            colors[bad, 4:8] = GREY + (1.0,)
        status = np.tile(np.asarray(HIDDEN, dtype=np.float32), (6, 1))
        saturated = np.abs(np.nan_to_num(force)) >= mech.max_force * (1.0 - 1e-9)
        status[saturated] = SATURATED
        if lengths is not None:
            endstop = ~((mech.leg_length_min < L) & (L < mech.leg_length_max))
            status[endstop] = ENDSTOP
        colors[:, 8:12] = status
        if ghost is not self._ghost_key:        # changes seldom: flattened once
            self._ghost_key = ghost
            self._ghost_flat = flatten(self.ghost_shapes(ghost))
        g8, g4 = self._ghost_flat
        f8[o['ghost']:] = g8
        f4[-8:] = g4
        return f8, f4

    def _flat_static(self):
        """Copies of the numbers that never change, and where the rest go."""
        if not hasattr(self, '_static'):
            rot = np.eye(3)
            sample = self.shapes(self.mech.neutral_pose()[0], rot)
            f8, f4 = flatten(sample)
            o, at = {}, 0
            for shape in sample:
                key = shape.ns if shape.ns not in ('cylinder', 'piston', 'leg_status') else 'legs'
                o.setdefault(key, at + 10)      # the points (or, for legs, the first pose)
                at += 10 + (0 if shape.kind in (CYLINDER, SPHERE) else shape.points.size)
            o['legs'] -= 10
            o['ghost'] -= 10
            self._offsets = o
            self._static = (f8, f4)
            self._ghost_key = self._ghost_flat = False
        return self._static[0].copy(), self._static[1].copy()

    def _two_sided(self, verts) -> np.ndarray:
        """The plate's triangles in both windings, so that it shows from below too."""
        faces = self.plate_faces
        order = np.concatenate([faces.ravel(), faces[:, [0, 2, 1]].ravel()])
        return np.asarray(verts, dtype=float)[order]

    def ghost_shapes(self, ghost: tuple[ArrayLike, ArrayLike] | None) -> list[Shape]:
        """The setpoint pose: a translucent plate and thin legs to it.

        Args:
            ghost: (position (3,), rot (3, 3)); None: both shapes hidden.

        Returns:
            The two shapes ``ghost`` and ``ghost_legs``.
        """
        if ghost is None:
            points = np.zeros((6 * len(self.plate_faces), 3))
            return [Shape('ghost', 0, TRIANGLE_LIST, HIDDEN, points=points),
                    Shape('ghost_legs', 0, LINE_LIST, HIDDEN, (0.006, 1.0, 1.0),
                          points=np.zeros((12, 3)))]
        verts = self.vertices(*ghost)
        base = np.asarray(self.mech.base_points, dtype=float)
        legs = np.empty((12, 3))
        legs[0::2] = base
        legs[1::2] = verts[self._leg_joint]
        return [Shape('ghost', 0, TRIANGLE_LIST, (0.95, 0.75, 0.20, 0.35),
                      points=self._two_sided(verts)),
                Shape('ghost_legs', 0, LINE_LIST, (0.95, 0.75, 0.20, 0.5),
                      (0.006, 1.0, 1.0), points=legs)]


def flatten(shape_list: list[Shape]) -> tuple[np.ndarray, np.ndarray]:
    """The numbers of ``shape_list`` in marker order. ``Scene.flat`` computes
    the same numbers directly, without Shape objects.

    Args:
        shape_list: the shapes.

    Returns:
        (float64 vector: per shape position (3), orientation (4), scale (3),
        then the points of a list kind; float32 colours: r, g, b, a per shape).
    """
    f8, f4 = [], []
    for shape in shape_list:
        if shape.kind in (CYLINDER, SPHERE):
            f8 += [*shape.position, *shape.orientation, *shape.scale]
        else:
            f8 += [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, *shape.scale]
            f8 += list(np.ravel(shape.points))
        f4 += list(shape.color)
    return np.array(f8, dtype=float), np.array(f4, dtype=np.float32)


def plate_faces(points: ArrayLike) -> np.ndarray:
    """The platform plate's triangles: a 6-3's one triangle (0, 1, 2); a 6-6's
    hexagon, its joints in turn about their centre (in the plane they span)
    and fanned from the first.

    Args:
        points: (3, 3) or (6, 3) ``platform_points``.

    Returns:
        (1, 3) or (4, 3) int, rows of indices into ``points``.
    """
    points = np.asarray(points, dtype=float)
    if len(points) == 3:
        return np.array([[0, 1, 2]])
    centred = points - points.mean(axis=0)
    u, v, _ = np.linalg.svd(centred)[2]          # the joints' plane: u, v in it
    ring = np.argsort(np.arctan2(centred @ v, centred @ u))
    return np.array([[ring[0], ring[j], ring[j + 1]] for j in range(1, len(ring) - 1)])


def _cylinder(ns, i, start, end, diameter, color) -> Shape:
    axis = end - start
    length = float(np.linalg.norm(axis))
    orientation = quaternion_z_to(axis) if length > 0 else np.array([0.0, 0.0, 0.0, 1.0])
    return Shape(ns, i, CYLINDER, color, (diameter, diameter, max(length, 1e-6)),
                 position=0.5 * (start + end), orientation=orientation,
                 points=np.array([start, end]))
