"""MP4 video of an episode, rendered off-screen with pyvista (optional extra ``softcrawl[video]``).

One video frame per recorded episode frame (``EpisodeResult.frames``, i.e. one per
``--frames-every`` steps), 25 frames per second: the outer surface of all bodies
(:func:`softcrawl.robot.animation.robot_surface`; disk grey, legs coloured by regulator as in
the design pictures), a floor grid (20 mm squares) at ``z = 0``, a camera that follows
the disk from a 3/4 view (front right, above), and a label with the time and the reward so far.

Without a display, VTK renders through EGL: unless ``VTK_DEFAULT_OPENGL_WINDOW`` is already set,
it is set to ``vtkEGLRenderWindow`` before pyvista is imported.
"""

from __future__ import annotations

import os

import numpy as np
from matplotlib.colors import to_hex

from softcrawl.design.picture import regulator_colour
from softcrawl.robot.animation import DISK_COLOUR, frame_caption, robot_surface
from softcrawl.robot.assembly import Robot
from softcrawl.robot.episode import MM_PER_CM, EpisodeResult

#: Video frame rate, frames per second.
FPS = 25
#: Default frame size, pixels (width, height).
SIZE = (640, 360)
#: Camera offset from the disk centre, mm (front right, above: a 3/4 view).
CAMERA_OFFSET = np.array([260.0, -340.0, 240.0])
_INSTALL = "pip install softcrawl[video]"


def _colors(n_regulators: int) -> list[str]:
    """The colour map of the surface's ``color`` values 0 (disk) .. R (regulator R's legs)."""
    return [to_hex(c) for c in (DISK_COLOUR, *(regulator_colour(k) for k in range(1, n_regulators + 1)))]


class VideoUnavailableError(ValueError):
    """pyvista / imageio-ffmpeg are missing or cannot render off-screen (a ValueError, so the CLI
    reports it as a one-line user error)."""


def _import():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    try:
        import imageio_ffmpeg
        import pyvista
    except ImportError as exc:
        raise VideoUnavailableError(f"--video needs pyvista and imageio-ffmpeg ({exc}); "
                                    f"install them with: {_INSTALL}") from None
    return pyvista, imageio_ffmpeg


def check_video_support() -> None:
    """Check, cheaply and before a simulation, that videos can be written: imports pyvista and
    imageio-ffmpeg and renders one tiny off-screen frame.

    Raises:
        VideoUnavailableError: a package is missing (the message names ``pip install
            softcrawl[video]``) or off-screen rendering fails.
    """
    pv, _ = _import()
    try:
        pl = pv.Plotter(off_screen=True, window_size=(32, 32))
        pl.add_mesh(pv.Sphere())
        pl.screenshot(return_img=True)
        pl.close()
    except Exception as exc:  # VTK raises plain RuntimeErrors (or worse) without a GL context
        raise VideoUnavailableError(f"off-screen rendering with pyvista failed ({exc}); VTK needs EGL "
                                    "(libEGL) or OSMesa, or a display") from exc


def write_video(path: str | os.PathLike, robot: Robot, result: EpisodeResult,
                size: tuple[int, int] = SIZE, fps: int = FPS) -> int:
    """Render the recorded frames of an episode to an H.264 MP4.

    Args:
        path: destination ``.mp4``.
        robot: the robot the episode ran (its meshes give the surfaces).
        result: the episode; ``result.frames`` ``(k, N, 3)`` mm at ``result.frame_times`` ``(k,)`` s.
        size: ``(width, height)`` pixels, both even.
        fps: frames per second of the video.

    Returns:
        The number of video frames written (``k``).

    Raises:
        VideoUnavailableError: pyvista / imageio-ffmpeg missing (see :func:`check_video_support`).
        ValueError: no recorded frames, or an odd frame size.
        OSError / RuntimeError: if ffmpeg fails to write the file.
    """
    pv, imageio_ffmpeg = _import()
    if len(result.frames) == 0:
        raise ValueError("the episode recorded no frames (record_every=None?); nothing to render")
    if size[0] % 2 or size[1] % 2:
        raise ValueError(f"video size must be even (H.264), got {size}")
    outer = robot_surface(robot)
    tris = outer.triangles
    surface = pv.PolyData(result.frames[0].astype(np.float64),
                          np.column_stack([np.full(len(tris), 3), tris]).ravel())
    surface.cell_data["color"] = outer.regulator  # disk 0, a leg its regulator
    disk = robot.model.body_slice(robot.disk_body)

    centre0 = result.frames[0][disk].mean(axis=0)
    x0 = robot.reward_position(result.frames[0])[0]
    floor = pv.Plane(center=(centre0[0], centre0[1], 0.0), i_size=1200, j_size=1200, i_resolution=60, j_resolution=60)
    pl = pv.Plotter(off_screen=True, window_size=tuple(size))
    try:
        pl.set_background("white")
        pl.add_mesh(floor, color="#f2efe6", show_edges=True, edge_color="#c9c4b5", lighting=False)
        n_reg = robot.model.n_channels
        pl.add_mesh(surface, scalars="color", cmap=_colors(n_reg), clim=(-0.5, n_reg + 0.5), n_colors=n_reg + 1,
                    show_scalar_bar=False, smooth_shading=False)
        label = pl.add_text("", position="upper_left", font_size=12, color="black")  # corner 2 = upper left
        writer = imageio_ffmpeg.write_frames(str(path), tuple(size), fps=fps, macro_block_size=2)
        writer.send(None)  # start ffmpeg
        try:
            for t, x in zip(result.frame_times, result.frames):
                surface.points = np.asarray(x, dtype=np.float64)
                centre = x[disk].mean(axis=0).astype(np.float64)
                pl.camera.focal_point = centre
                pl.camera.position = centre + CAMERA_OFFSET
                pl.camera.up = (0.0, 0.0, 1.0)
                label.SetText(2, frame_caption(t, (robot.reward_position(x)[0] - x0) / MM_PER_CM))
                pl.render()
                img = pl.screenshot(return_img=True)
                writer.send(np.ascontiguousarray(img[:, :, :3]))
        finally:
            writer.close()
    finally:
        pl.close()
    return len(result.frames)
