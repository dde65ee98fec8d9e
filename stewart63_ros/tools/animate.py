"""``plot --animate``: a run as an animation, the platform in 3D beside the leg lengths.

Drawn with matplotlib from the same shapes as the ``markers`` topic
(core/mechanics/markers.py): base, U-joints, each leg's cylinder and piston (the piston
coloured by its force), the platform plate; beside it the six leg lengths
against time with a cursor. GIF through Pillow (matplotlib's ``pillow``
writer, always there), MP4 through ffmpeg where it is installed.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stewart63_ros.core.mechanics import markers

#: frames at most: a longer run is played faster (the title says how much)
MAX_FRAMES = 300


class Animator:
    """One figure, redrawn for each time of a run."""

    def __init__(self, columns: dict, mech, title: str = ''):
        import matplotlib  # lazy: matplotlib costs 425 ms; only a figure needs it
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt  # lazy: pyplot costs 794 ms; only a figure needs it

        # lazy: mplot3d, core.mechanics.rotation cost 1186 ms; only --animate needs them
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        from stewart63_ros.core.mechanics.rotation import rotation_from_euler
        self.plt = plt
        self.mech = mech
        self.scene = markers.Scene(mech)
        self.t = np.asarray(columns['t'], dtype=float)
        pose_cols = ('x', 'y', 'z', 'theta_x', 'theta_y', 'theta_z')
        pose = np.column_stack([columns[c] for c in pose_cols])
        ok = np.all(np.isfinite(pose), axis=1)
        if not ok.any():
            raise ValueError('no platform poses in the run: nothing to animate')
        self.t, pose = self.t[ok], pose[ok]
        self.position = pose[:, :3]
        self.rot = [rotation_from_euler(th) for th in pose[:, 3:]]
        # A sensor dropout leaves NaN lengths: drawn as gaps in the panel, and
        # the leg at its pose's length in 3D (never a whole panel lost).
        lengths = np.column_stack([columns['L%d' % i] for i in range(1, 7)])[ok]
        self.lengths = lengths if np.isfinite(lengths).any() else None
        forces = np.column_stack([columns['F%d' % i] for i in range(1, 7)])[ok]
        self.forces = forces
        self.title = title

        self.fig = plt.figure(figsize=(10, 4.6), dpi=90)
        self.ax3 = self.fig.add_subplot(1, 2, 1, projection='3d')
        self.axL = self.fig.add_subplot(1, 2, 2)
        ax3 = self.ax3
        r = self.scene.base_radius * 1.05
        ax3.set_xlim(-r, r)
        ax3.set_ylim(-r, r)
        ax3.set_zlim(0, float(np.nanmax(self.position[:, 2])) + 0.4)
        ax3.set_box_aspect((1, 1, ax3.get_zlim()[1] / (2 * r)))
        ax3.set_xlabel('x [m]')
        ax3.set_ylabel('y [m]')
        ax3.set_zlabel('z [m]')
        ax3.view_init(elev=22, azim=-50)
        base = np.asarray(mech.base_points)
        ax3.scatter(base[:, 0], base[:, 1], base[:, 2], color='0.15', s=18)
        ang = np.linspace(0, 2 * np.pi, 60)
        ax3.plot(1.1 * r * np.cos(ang), 1.1 * r * np.sin(ang), 0 * ang, color='0.5', lw=0.8)
        self.cyl_lines = [ax3.plot([], [], [], color='0.25', lw=5, solid_capstyle='round')[0]
                          for _ in range(6)]
        self.rod_lines = [ax3.plot([], [], [], lw=2.5)[0] for _ in range(6)]
        self.plate = Poly3DCollection([np.zeros((3, 3))], facecolor=(0.2, 0.65, 0.35, 0.85),
                                      edgecolor='k')
        ax3.add_collection3d(self.plate)
        self.text = ax3.text2D(0.02, 0.95, '', transform=ax3.transAxes)

        axL = self.axL
        if self.lengths is not None:
            for i in range(6):
                axL.plot(self.t, self.lengths[:, i], label='$L_%d$' % (i + 1))
        axL.axhline(mech.leg_length_min, color='0.6', ls=':', lw=0.8,
                    label='stroke' if self.lengths is None else None)
        axL.axhline(mech.leg_length_max, color='0.6', ls=':', lw=0.8)
        if self.t[-1] > self.t[0]:
            axL.set_xlim(self.t[0], self.t[-1])
        axL.set_xlabel('time [s]')
        axL.set_ylabel('leg length [m]')
        axL.grid(True, alpha=0.3)
        axL.legend(loc='best', fontsize='small', ncol=3)
        self.cursor = axL.axvline(self.t[0], color='k', lw=1)
        self.fig.suptitle(title)
        self.fig.tight_layout()

    def index(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t, side='right') - 1, 0, len(self.t) - 1))

    def draw(self, t: float):
        """Move every artist to time ``t``; returns them."""
        k = self.index(t)
        lengths = None if self.lengths is None else self.lengths[k]
        if lengths is not None and not np.all(np.isfinite(lengths)):
            base, _, tip = self.scene.legs(self.position[k], self.rot[k])
            lengths = np.where(np.isfinite(lengths), lengths,
                               np.linalg.norm(tip - base, axis=1))     # the pose's own
        forces = self.forces[k] if np.all(np.isfinite(self.forces[k])) else None
        shapes = {(s.ns, s.id): s for s in self.scene.shapes(
            self.position[k], self.rot[k], lengths, forces)}
        for i in range(6):
            a, b = shapes[('cylinder', i)].points
            self.cyl_lines[i].set_data_3d([a[0], b[0]], [a[1], b[1]], [a[2], b[2]])
            rod = shapes[('piston', i)]
            a, b = rod.points
            self.rod_lines[i].set_data_3d([a[0], b[0]], [a[1], b[1]], [a[2], b[2]])
            status = shapes[('leg_status', i)]
            self.rod_lines[i].set_color(status.color[:3] if status.color[3] > 0
                                        else rod.color[:3])
        # the plate's outline: a 6-3's triangle, a 6-6's hexagon (its joints in turn)
        faces = self.scene.plate_faces
        ring = np.concatenate([faces[:, 0][:1], faces[:, 1], faces[-1:, 2]])
        self.plate.set_verts([shapes[('platform_joints', 0)].points[ring]])
        self.cursor.set_xdata([self.t[k], self.t[k]])
        self.text.set_text('t = %.2f s   z = %.3f m' % (self.t[k], self.position[k][2]))
        return self.cyl_lines + self.rod_lines + [self.plate, self.cursor, self.text]

    def save_frame(self, t: float, path) -> Path:
        self.draw(t)
        self.fig.savefig(path)
        return Path(path)

    def save(self, path, fps: float = 15.0) -> tuple[Path, int, float]:
        """Write the animation; (path, frames, speed-up over real time)."""
        from matplotlib import animation  # lazy: matplotlib costs 794 ms; only a figure needs it
        path = Path(path)
        span = float(self.t[-1] - self.t[0])
        frames = max(2, min(MAX_FRAMES, int(span * fps) + 1))
        speed = max(1.0, span * fps / (frames - 1)) if span > 0 else 1.0
        times = np.linspace(self.t[0], self.t[-1], frames)
        anim = animation.FuncAnimation(self.fig, lambda t: self.draw(t), frames=times,
                                       blit=False)
        if path.suffix.lower() == '.gif':
            writer = animation.PillowWriter(fps=fps)
        elif path.suffix.lower() == '.mp4':
            if not animation.FFMpegWriter.isAvailable():
                raise ValueError('MP4 needs ffmpeg, which is not installed; write a .gif')
            writer = animation.FFMpegWriter(fps=fps)
        else:
            raise ValueError('%s: the animation is written as .gif or .mp4' % path)
        anim.save(str(path), writer=writer)
        self.plt.close(self.fig)
        return path, frames, speed
