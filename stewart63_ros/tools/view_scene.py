"""The view's 3D scene (viser): the base, the legs, the platform and its
ghost, drawn from the markers every view shares (core/mechanics/markers.py).
"""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.mechanics import markers as shapes_mod
from stewart63_ros.core.mechanics.rotation import (
    quaternion_from_rotation,
)

#: Browser update rate [Hz]: viser pushes every change over a websocket; at
#: 1 kHz the page stops following, at 30 Hz it follows (measured).

#: Browser update rate [Hz]: viser pushes every change over a websocket; at
#: 1 kHz the page stops following, at 30 Hz it follows (measured).
FRAME_RATE = 30.0
PANEL_PERIOD = 0.25          # s between updates of the numbers on the page
NO_RIG_AFTER = 3.0           # s without a pose before the page says "no rig"
REFUSED = (0.85, 0.1, 0.1)


def rgb(color) -> tuple:
    return tuple(int(round(255 * c)) for c in color[:3])


class ViewScene:
    """The rig's shapes as viser scene nodes, made once and moved per frame."""

    def __init__(self, server, setup):
        self.server = server
        self.mech = mech = setup.mechanism
        self.scene = shapes_mod.Scene(mech)
        sc = server.scene
        sc.set_up_direction('+z')
        server.initial_camera.position = (2.6, -2.4, 3.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.7)
        sc.add_grid('/grid', width=6.0, height=6.0, cell_size=0.5, position=(0, 0, -0.025))
        shapes = self.scene.shapes(setup.task.initial_position, np.eye(3))
        by = {(s.ns, s.id): s for s in shapes}
        base = by[('base', 0)]
        sc.add_cylinder('/base', radius=base.scale[0] / 2, height=base.scale[2],
                        color=rgb(base.color), position=tuple(base.position))
        for i, p in enumerate(mech.base_points):
            sc.add_icosphere('/ujoint_%d' % (i + 1), radius=self.scene.joint_d / 2,
                             color=rgb(by[('ujoints', 0)].color), position=tuple(p))
        # a 6-3's triangle and three vertices, a 6-6's hexagon and six joints
        plat = np.asarray(mech.platform_points, dtype=float)
        faces = self.scene.plate_faces
        # Hidden until the first state: a page with no rig shows the base only.
        self.platform = sc.add_frame('/platform', show_axes=True, axes_length=0.25,
                                     axes_radius=0.01, visible=False)
        sc.add_mesh_simple('/platform/plate', plat, faces, side='double',
                           color=rgb(by[('platform', 0)].color))
        for k, p in enumerate(plat):
            sc.add_icosphere('/platform/joint_%d' % (k + 1), radius=self.scene.joint_d / 2,
                             color=rgb(by[('platform_joints', 0)].color), position=tuple(p))
        self.ghost = sc.add_frame('/ghost', show_axes=False, visible=False)
        self.ghost_mesh = sc.add_mesh_simple('/ghost/plate', plat, faces, side='double',
                                             color=rgb(shapes_mod.ENDSTOP), opacity=0.35)
        self.cylinders, self.pistons, self.status = [], [], []
        for i in range(6):
            c, p, s = by[('cylinder', i)], by[('piston', i)], by[('leg_status', i)]
            self.cylinders.append(sc.add_cylinder(
                '/cylinder_%d' % (i + 1), radius=c.scale[0] / 2, height=c.scale[2],
                color=rgb(c.color), position=tuple(c.position), wxyz=_wxyz(c.orientation),
                visible=False))
            self.pistons.append(sc.add_cylinder(
                '/piston_%d' % (i + 1), radius=p.scale[0] / 2, height=p.scale[2],
                color=rgb(p.color), position=tuple(p.position), wxyz=_wxyz(p.orientation),
                visible=False))
            self.status.append(sc.add_icosphere(
                '/leg_status_%d' % (i + 1), radius=s.scale[0] / 2, color=rgb(shapes_mod.ENDSTOP),
                position=tuple(s.position), visible=False))
        self._ghost_pose = None
        self.shown = False

    def update(self, position, rot, lengths=None, forces=None):
        """Move everything to one state (call at most FRAME_RATE times a second)."""
        shapes = self.scene.shapes(position, rot, lengths, forces)
        by = {(s.ns, s.id): s for s in shapes}
        with self.server.atomic():
            self.platform.position = tuple(np.asarray(position, dtype=float))
            self.platform.wxyz = _wxyz(quaternion_from_rotation(rot))
            for i in range(6):
                for handle, shape in ((self.cylinders[i], by[('cylinder', i)]),
                                      (self.pistons[i], by[('piston', i)])):
                    handle.position = tuple(shape.position)
                    handle.wxyz = _wxyz(shape.orientation)
                    handle.height = float(shape.scale[2])
                    color = rgb(shape.color)
                    if tuple(handle.color) != color:
                        handle.color = color
                status = by[('leg_status', i)]
                shown = status.color[3] > 0
                self.status[i].position = tuple(status.position)
                if shown:
                    self.status[i].color = rgb(status.color)
                if self.status[i].visible != shown:
                    self.status[i].visible = shown
            if not self.shown:
                self.shown = True
                for handle in [self.platform] + self.cylinders + self.pistons:
                    handle.visible = True

    def set_ghost(self, pose, refused=False):
        """The setpoint pose (position, rot), or None to hide it."""
        key = None if pose is None else (tuple(np.round(pose[0], 9)),
                                         tuple(np.round(np.ravel(pose[1]), 9)), refused)
        if key == self._ghost_pose:
            return
        self._ghost_pose = key
        if pose is None:
            self.ghost.visible = False
            return
        self.ghost.position = tuple(np.asarray(pose[0], dtype=float))
        self.ghost.wxyz = _wxyz(quaternion_from_rotation(pose[1]))
        self.ghost_mesh.color = rgb(REFUSED if refused else shapes_mod.ENDSTOP)
        self.ghost.visible = True


def _wxyz(quat_xyzw) -> tuple:
    x, y, z, w = (float(v) for v in quat_xyzw)
    return (w, x, y, z)


def _quat_xyzw(wxyz) -> np.ndarray:
    w, x, y, z = (float(v) for v in wxyz)
    return np.array([x, y, z, w])
