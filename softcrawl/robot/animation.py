"""Animated GIF of an episode, rendered headless with matplotlib (Agg) and written with Pillow.

:func:`write_animation` draws the robot's outer surface (the ``"boundary"`` triangles of each
body's tet mesh, :func:`robot_surface`) at up to :data:`MAX_FRAMES` of the episode's recorded
frames, evenly spaced in time, and plays them at :data:`FPS` (a 20 s episode recorded every
0.2 s becomes a 5 s time-lapse). Each frame: the disk grey, each leg in its regulator's colour
(:func:`softcrawl.design.picture.regulator_colour`) from pale at 0 kPa to full at
:data:`~softcrawl.gaits.pressure.P_MAX_KPA` (the applied pressure of that regulator at the
frame's time), flat-shaded by a fixed light; a 20 mm floor grid at ``z = 0`` fixed in the world,
so forward motion shows against it; an orthographic 3/4 view from the front right (elevation
:data:`ELEVATION_DEG`, azimuth :data:`AZIMUTH_DEG`) that follows the disk; a caption with the
time, the +x displacement of the disk's top centre and each used regulator's applied pressure
(in its colour).

Faces turned away from the camera are dropped before drawing (the surface is closed and the
view orthographic, so they are hidden anyway): matplotlib's painter's algorithm then sorts about
half the triangles. Only matplotlib and Pillow (a matplotlib dependency) are used; no display, GPU
or pyplot state is needed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from softcrawl.design.picture import regulator_colour
from softcrawl.gaits.pressure import P_MAX_KPA
from softcrawl.geometry.mesh import boundary_triangles
from softcrawl.robot.assembly import Robot
from softcrawl.robot.episode import MM_PER_CM, EpisodeResult

#: Frames per second of the GIF (a GIF stores frame durations in whole 10 ms).
FPS = 10
#: Most frames drawn (recorded frames are subsampled evenly in time): 5 s at :data:`FPS`.
MAX_FRAMES = 50
#: Default image size, pixels (width, height).
SIZE = (480, 320)
#: Camera elevation above the floor and azimuth from +x (counter-clockwise seen from above), degrees.
ELEVATION_DEG, AZIMUTH_DEG = 28.0, -55.0
#: Floor grid spacing, mm.
GRID_MM = 20.0
#: Colour of the disk (and of every body driven by no regulator).
DISK_COLOUR = "#9a9a9a"


@dataclass(frozen=True, eq=False)
class RobotSurface:
    """The outer surface of a robot's bodies, in the model's global node numbering.

    Attributes:
        triangles: ``(k, 3)`` int64 global node indices, outward normals
            (``(x1 - x0) x (x2 - x0)``).
        regulator: ``(k,)`` int64: the regulator (1..R of the robot's space) driving the
            triangle's leg, 0 for the disk.
    """

    triangles: np.ndarray
    regulator: np.ndarray


def robot_surface(robot: Robot) -> RobotSurface:
    """The outer surface of ``robot``: each body's ``"boundary"`` surface tag (the outer skin;
    a PneuNet's cavity walls are left out), or its tet mesh's boundary faces
    (:func:`softcrawl.geometry.mesh.boundary_triangles`) for a mesh without that tag."""
    model = robot.model
    regulator_of = {leg.body: leg.regulator for leg in robot.legs}
    tris, owner = [], []
    for i, (body, off) in enumerate(zip(model.bodies, model.node_offsets)):
        tri = body.mesh.surfaces.get("boundary")
        if tri is None or len(tri) == 0:
            tri = boundary_triangles(body.mesh.tets)
        tris.append(tri + off)
        owner.append(np.full(len(tri), regulator_of.get(i, 0), np.int64))
    return RobotSurface(np.concatenate(tris).astype(np.int64), np.concatenate(owner))


def frame_caption(t: float, dx_cm: float) -> str:
    """Caption of a frame at time ``t`` (s) with the disk's +x displacement ``dx_cm`` (cm)."""
    return f"t = {t:5.2f} s   x = {dx_cm:+.2f} cm"


def frame_indices(n_recorded: int, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """``(m,)`` indices of the recorded frames to draw: all ``n_recorded`` if at most
    ``max_frames``, else ``max_frames`` evenly spaced ones from the first to the last.

    Raises:
        ValueError: ``n_recorded`` or ``max_frames`` < 1.
    """
    if n_recorded < 1:
        raise ValueError("the episode recorded no frames (record_every=None, or it diverged while settling); "
                         "nothing to animate")
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1:
        raise ValueError(f"max_frames must be an integer >= 1, got {max_frames!r}")
    return np.unique(np.round(np.linspace(0, n_recorded - 1, min(n_recorded, max_frames))).astype(np.int64))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-12)


def _check(result: EpisodeResult, n_nodes: int, fps, size) -> None:
    frames = result.frames
    if frames.ndim != 3 or frames.shape[1:] != (n_nodes, 3):
        raise ValueError(f"frames must have shape (k, {n_nodes}, 3) for this robot, got {frames.shape}")
    finite = np.isfinite(frames).all(axis=(1, 2))
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(f"frame {i} (t = {result.frame_times[i]:g} s) has non-finite node positions; "
                         "cannot animate it")
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.number)) or not (0 < fps <= 100):
        raise ValueError(f"fps must be in (0, 100], got {fps!r}")
    pair = isinstance(size, (tuple, list)) and len(size) == 2
    if not pair or not all(isinstance(s, (int, np.integer)) and 64 <= s <= 4096 for s in size):
        raise ValueError(f"size must be (width, height) with integers in [64, 4096] pixels, got {size!r}")


class _Renderer:
    """One figure, reused for every frame."""

    def __init__(self, robot: Robot, surface: RobotSurface, first: np.ndarray, size: tuple[int, int],
                 regulators: list[int]):
        from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

        self.surface = surface
        self.disk = robot.model.body_slice(robot.disk_body)
        lo, hi = first[:, :2].min(axis=0), first[:, :2].max(axis=0)
        # the camera aims at the robot's footprint centre in the first frame, moved with the disk
        self.offset = 0.5 * (lo + hi) - first[self.disk, :2].mean(axis=0)
        self.radius = 0.5 * float((hi - lo).max()) * 1.1
        self.height = float(first[:, 2].max()) * 1.6
        e, a = np.radians(ELEVATION_DEG), np.radians(AZIMUTH_DEG)
        self.eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        self.light = _unit(self.eye + np.array([-0.4, 0.2, 1.2]))
        self.base = np.array([to_rgb(regulator_colour(int(r)) if r else DISK_COLOUR) for r in surface.regulator])
        self.is_leg = surface.regulator > 0

        dpi = 100
        self.fig = Figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        ax = self.fig.add_axes((0.0, 0.0, 1.0, 1.0), projection="3d", computed_zorder=False)
        ax.set_proj_type("ortho")
        ax.view_init(elev=ELEVATION_DEG, azim=AZIMUTH_DEG)
        ax.set_axis_off()
        ax.set_box_aspect((2 * self.radius, 2 * self.radius, self.height), zoom=1.5)  # equal mm on every axis
        self.ax = ax
        self.floor = Line3DCollection([], colors="#c9c4b5", linewidths=0.6, zorder=0)
        ax.add_collection3d(self.floor, autolim=False)
        self.body = Poly3DCollection([], linewidths=0.0, antialiased=False, zorder=1)
        ax.add_collection3d(self.body, autolim=False)
        font = dict(ha="left", va="top", family="monospace", fontsize=max(5.0, 9.0 * size[1] / SIZE[1]))
        self.caption = self.fig.text(0.02, 0.97, "", **font)
        # one label per used regulator, in its legs' colour
        self.labels = {k: self.fig.text(0.02 + 0.3 * j, 0.90, "", color=regulator_colour(k), **font)
                       for j, k in enumerate(regulators)}

    def _grid(self, cx: float, cy: float) -> np.ndarray:
        r = self.radius
        xs = np.arange(np.ceil((cx - r) / GRID_MM), np.floor((cx + r) / GRID_MM) + 1) * GRID_MM
        ys = np.arange(np.ceil((cy - r) / GRID_MM), np.floor((cy + r) / GRID_MM) + 1) * GRID_MM
        lx = [[(x, cy - r, 0.0), (x, cy + r, 0.0)] for x in xs]
        ly = [[(cx - r, y, 0.0), (cx + r, y, 0.0)] for y in ys]
        return np.array(lx + ly)

    def draw(self, x: np.ndarray, pressure_kpa: np.ndarray, caption: str) -> np.ndarray:
        """Render one frame: ``x`` ``(N, 3)`` mm, ``pressure_kpa`` ``(R,)`` applied real kPa
        (regulators 1..R), ``caption`` above the pressures; returns the ``(height, width, 3)``
        uint8 image."""
        cx, cy = x[self.disk, :2].mean(axis=0) + self.offset
        r = self.radius
        self.ax.set_xlim(cx - r, cx + r)
        self.ax.set_ylim(cy - r, cy + r)
        self.ax.set_zlim(0.0, self.height)
        self.floor.set_segments(self._grid(cx, cy))
        verts = x[self.surface.triangles]
        normal = _unit(np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]))
        front = normal @ self.eye > 0
        fill = np.where(self.is_leg, 0.3 + 0.7 * np.clip(pressure_kpa[self.surface.regulator - 1] / P_MAX_KPA, 0, 1),
                        1.0)[:, None]
        colour = 1.0 - fill * (1.0 - self.base)  # pale (low pressure) to the full colour
        shade = 0.55 + 0.45 * np.clip(normal @ self.light, 0.0, 1.0)[:, None]
        self.body.set_verts(verts[front])
        self.body.set_facecolor(np.clip(colour[front] * shade[front], 0, 1))
        self.caption.set_text(caption)
        for k, label in self.labels.items():
            label.set_text(f"p{k} = {pressure_kpa[k - 1]:4.1f} kPa")
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[:, :, :3].copy()


def write_animation(path: str | os.PathLike, robot: Robot, result: EpisodeResult, fps: float = FPS,
                    max_frames: int = MAX_FRAMES, size: tuple[int, int] = SIZE) -> int:
    """Render the recorded frames of an episode to an animated GIF (module docstring).

    Args:
        path: destination ``.gif`` (written in place; callers stage it, see
            :func:`softcrawl.robot.output.write_results`).
        robot: the robot the episode ran (its meshes give the surface).
        result: the episode; ``result.frames`` ``(k, N, 3)`` mm at ``result.frame_times`` ``(k,)``
            s; ``result.applied`` ``(n + 1, R)`` real kPa at ``result.time`` colours the legs.
        fps: frames per second of the GIF, in (0, 100].
        max_frames: most frames drawn (>= 1); more recorded frames are subsampled evenly.
        size: ``(width, height)`` pixels, integers in [64, 4096].

    Returns:
        The number of GIF frames written.

    Raises:
        ValueError: no recorded frames, ``max_frames`` < 1, frames of another robot or with
            non-finite positions, or a bad ``fps`` / ``size`` (checked before anything is drawn).
        OSError: if the file cannot be written.
    """
    from PIL import Image

    idx = frame_indices(len(result.frames), max_frames)
    _check(result, robot.model.n_nodes, fps, size)
    frames = result.frames
    renderer = _Renderer(robot, robot_surface(robot), frames[0].astype(np.float64), size,
                         sorted({leg.regulator for leg in robot.legs}))
    x0 = robot.reward_position(frames[0])[0]
    times = result.frame_times[idx]
    applied = np.column_stack([np.interp(times, result.time, col) for col in result.applied.T])
    images = []
    for t, i, p in zip(times, idx, applied):
        x = frames[i].astype(np.float64)
        caption = frame_caption(t, (robot.reward_position(x)[0] - x0) / MM_PER_CM)
        image = Image.fromarray(renderer.draw(x, p, caption))
        images.append(image.quantize(colors=128, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE))
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return len(images)
