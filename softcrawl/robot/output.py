"""Writing the results of ``softcrawl simulate``: summary, trajectory, plot, ParaView series.

Layout of an output directory:

- ``summary.json``: design, gait, reward, timing, model size, solver statistics, version.
- ``trajectory.npz`` / ``trajectory.csv``: per step ``t, x, y, z`` (disk top centre, mm),
  ``cmd_1..R`` and ``applied_1..R`` (real kPa; ``R`` regulators of the robot's space, 3 in the
  paper's), ``contacts``.
- ``trajectory.png``: displacement x(t) in cm and pressures vs t (commanded dashed,
  applied solid).
- ``crawl.pvd`` + ``frames/frame_NNNNN.vtu``: all bodies' tetrahedra in one grid per frame
  with point field ``"displacement"`` (mm, from rest) and cell field ``"body"``.
- ``crawl.gif`` (only with ``animation=True``): the robot crawling, a few seconds drawn from
  the recorded frames with matplotlib (:mod:`softcrawl.robot.animation`).
- ``crawl.mp4`` (only with ``video=True``; needs ``softcrawl[video]``): the recorded frames
  rendered off-screen, 25 fps (:mod:`softcrawl.robot.video`).

Everything is written into a hidden temporary directory next to the destination and
renamed onto it only when complete (:func:`staged_directory`), so a failed run leaves no
partial directory that looks like a result. A full disk or a read-only file system after a long
run does not lose it: the staged directory keeps what was written, the essential results go
to a ``softcrawl-rescue-*`` folder of the system's temporary directory, and the one-line error
names both (:class:`OutputWriteError`). ``--overwrite`` replaces only folders softcrawl wrote
(:data:`OUTPUT_MARKER`).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from softcrawl import __version__
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.robot.animation import write_animation
from softcrawl.robot.assembly import Robot
from softcrawl.robot.episode import MM_PER_CM, EpisodeResult



def csv_columns(n_regulators: int) -> tuple[str, ...]:
    """Columns of ``trajectory.csv`` of a robot with ``n_regulators`` regulators."""
    regs = range(1, int(n_regulators) + 1)
    return ("t", "x", "y", "z", *(f"cmd_{k}" for k in regs), *(f"applied_{k}" for k in regs), "contacts")


#: Columns of ``trajectory.csv`` in the paper's space (3 regulators).
CSV_COLUMNS = csv_columns(3)


class OutputExistsError(ValueError):
    """The output path exists and overwriting was not requested (or it is not a directory)."""


#: Marker file in every output folder softcrawl writes; ``overwrite`` replaces only such folders.
OUTPUT_MARKER = ".softcrawl-output"


class OutputWriteError(ValueError):
    """Writing the outputs failed for lack of space or a read-only file system; the message
    names the folder where what was written is kept."""


def mark_output(folder: Path) -> None:
    """Mark ``folder`` as written by softcrawl (:data:`OUTPUT_MARKER`), so that a later command's
    ``--overwrite`` may replace it and nothing else."""
    (folder / OUTPUT_MARKER).write_text("written by softcrawl; --overwrite may replace this folder\n")


def check_output_path(out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Validate a destination directory before any work is done (creates nothing).

    ``out`` must name a folder (not ``.``/``..``) whose nearest existing ancestor is a writable
    directory; an existing ``out`` is accepted only with ``overwrite`` and only if it is empty
    or softcrawl wrote it (:data:`OUTPUT_MARKER`).

    Returns:
        ``out`` as a Path.

    Raises:
        OutputExistsError: ``out`` exists and ``overwrite`` is False, exists and is not a
            directory, or is not a softcrawl output; ``out`` is ``.``, or it cannot be created
            or written (an ancestor is a file, or not writable).
    """
    out = Path(out)
    if out.name in ("", ".", ".."):
        raise OutputExistsError(f"{str(out) or '.'}: give a new folder as the output, not the current or a parent one")
    if out.exists() or out.is_symlink():
        if not out.is_dir() or out.is_symlink():
            raise OutputExistsError(f"{out} exists and is not a directory")
        if not overwrite:
            raise OutputExistsError(f"{out} already exists (use --overwrite to replace it)")
        if not (out / OUTPUT_MARKER).is_file() and any(out.iterdir()):
            raise OutputExistsError(f"{out} is not a softcrawl output (no {OUTPUT_MARKER}); --overwrite only "
                                    "replaces folders softcrawl wrote")
    parent = out.absolute().parent
    while not parent.exists() and not parent.is_symlink() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputExistsError(f"cannot create {out}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputExistsError(f"cannot create {out}: {parent} is not writable")
    return out


#: ``errno`` values of "the disk is full" (space, quota) and "the file system is read-only".
NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


def rescue_directory(name: str) -> Path:
    """A fresh ``softcrawl-rescue-<name>-*`` folder in the system's temporary directory
    (``$TMPDIR``; often another file system than the output's): where results go that could
    not be written where they belong (OSError if it cannot be created either)."""
    return Path(tempfile.mkdtemp(prefix=f"softcrawl-rescue-{name}-"))


@contextlib.contextmanager
def staged_directory(out: str | os.PathLike, overwrite: bool = False,
                     rescue: Callable[[Path], None] | None = None) -> Iterator[Path]:
    """Yield a fresh temporary directory next to ``out``; on success move it onto ``out``.

    On an exception the temporary directory is removed and ``out`` is left untouched, except
    for a full disk or read-only file system (:data:`NO_SPACE_ERRNOS`), also when the temporary
    directory cannot even be created: then what was written is kept there, ``rescue`` (if
    given) writes the essential results into a :func:`rescue_directory`, and the
    :class:`OutputWriteError` names both. With ``overwrite``, an existing softcrawl output
    ``out`` is replaced (after the new one is complete). The result holds :data:`OUTPUT_MARKER`.

    Raises:
        OutputExistsError: see :func:`check_output_path` (checked again at the end).
        OutputWriteError: disk full / quota / read-only file system while writing.
    """
    out = check_output_path(out, overwrite)
    tmp = None
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the result should not be
        mark_output(tmp)
        yield tmp
        check_output_path(out, overwrite)
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / "dir")
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        if exc.errno not in NO_SPACE_ERRNOS:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
            raise
        kept = []
        try:
            written = tmp is not None and any(p.name != OUTPUT_MARKER for p in tmp.iterdir())
        except OSError:
            written = False
        if written:
            kept.append(f"what was written is kept in {tmp}")
        elif tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        if rescue is not None:
            try:
                saved = rescue_directory(out.name)
            except OSError:
                saved = None
            if saved is not None:
                try:
                    rescue(saved)
                except OSError:
                    shutil.rmtree(saved, ignore_errors=True)
                    saved = None
            kept.append(f"the results are saved in {saved}" if saved is not None else
                        "the results could not be saved elsewhere either")
        raise OutputWriteError(f"cannot write {out}: {exc.strerror or exc}; "
                               + ("; ".join(kept) or "nothing was kept")) from None
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        raise


def jsonable(v):
    """Convert numpy values/arrays and non-finite floats (-> None) for JSON."""
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, (list, tuple)):
        return [jsonable(u) for u in v]
    if isinstance(v, dict):
        return {str(k): jsonable(u) for k, u in v.items()}
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def describe_gait(gait) -> dict:
    """JSON-ready description of a gait: ``{"type": class name, **dataclass fields}``
    (arrays as lists, a gait inside a gait described in turn), or ``{"type", "repr"}`` for
    other objects."""
    if dataclasses.is_dataclass(gait):
        fields = {f.name: describe_gait(v) if dataclasses.is_dataclass(v) else v
                  for f in dataclasses.fields(gait) for v in (getattr(gait, f.name),)}
    else:
        fields = {"repr": repr(gait)}
    return jsonable({"type": type(gait).__name__, **fields})


def summary(robot: Robot, gait, result: EpisodeResult, calibration: PressureCalibration) -> dict:
    """The content of ``summary.json`` (JSON-ready dict; non-finite numbers become null)."""
    bodies = robot.model.bodies
    leg = bodies[robot.leg_bodies[0]].mesh
    disk = bodies[robot.disk_body].mesh
    steps = slice(1, None)  # episode steps (row 0 is the settled state)
    return jsonable({
        "design": list(robot.design),
        "gait": describe_gait(gait),
        "reward_cm": None if result.diverged else result.reward_cm,  # a diverged run has no reward
        "displacement_cm": result.reward_cm,
        "steps": result.steps,
        "sim_seconds": result.sim_seconds,
        "wall_seconds": result.wall_seconds,
        "real_time_factor": result.real_time_factor,
        "diverged": result.diverged,
        "divergence_reason": result.reason,
        "settling": result.settled,
        "model": robot.config.model,
        "config": dataclasses.asdict(robot.config),
        "calibration": {"a": calibration.a, "b": calibration.b},
        "mesh": {
            "leg_mesh_size": robot.config.leg_mesh_size, "disk_mesh_size": robot.config.disk_mesh_size,
            "nodes": robot.model.n_nodes, "tets": sum(b.mesh.n_tets for b in bodies),
            "leg_nodes": leg.n_nodes, "leg_tets": leg.n_tets, "disk_nodes": disk.n_nodes, "disk_tets": disk.n_tets,
        },
        "solver": {
            "mean_contacts": float(result.contacts[steps].mean()) if result.steps else None,
            "max_contacts": int(result.contacts[steps].max()) if result.steps else None,
            "mean_contact_sweeps": float(result.contact_sweeps[steps].mean()) if result.steps else None,
            "factorizations": result.factorizations,
        },
        "softcrawl_version": __version__,
    })


def trajectory_table(result: EpisodeResult) -> np.ndarray:
    """``(n + 1, 5 + 2 R)`` float array with the columns :func:`csv_columns` of ``R`` regulators
    (:data:`CSV_COLUMNS`: ``(n + 1, 11)`` in the paper's space)."""
    return np.column_stack([result.time, result.position, result.commanded, result.applied, result.contacts])


def write_trajectory(directory: Path, result: EpisodeResult) -> None:
    """Write ``trajectory.npz`` (named arrays) and ``trajectory.csv`` (header :func:`csv_columns`
    of the result's regulators)."""
    np.savez_compressed(
        directory / "trajectory.npz", t=result.time, position=result.position, commanded=result.commanded,
        applied=result.applied, contacts=result.contacts, contact_sweeps=result.contact_sweeps,
    )
    with (directory / "trajectory.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(csv_columns(result.commanded.shape[1]))
        for row in trajectory_table(result):
            w.writerow([f"{v:.6g}" for v in row[:-1]] + [int(row[-1])])


def plot_trajectory(path: Path, robot: Robot, result: EpisodeResult) -> None:
    """Save a two-panel PNG: disk x displacement (cm) vs t, and the used regulators'
    pressures vs t (commanded dashed, applied solid, real kPa)."""
    fig = Figure(figsize=(8, 6), layout="constrained")
    FigureCanvasAgg(fig)
    ax_x, ax_p = fig.subplots(2, 1, sharex=True)
    if len(result.time):
        ax_x.plot(result.time, (result.position[:, 0] - result.position[0, 0]) / MM_PER_CM, color="k")
    ax_x.set_ylabel("x displacement (cm)")
    title = f"design {','.join(map(str, robot.design))}: {result.reward_cm:+.2f} cm in {result.sim_seconds:g} s"
    ax_x.set_title(title + (" (DIVERGED)" if result.diverged else ""))
    ax_x.grid(alpha=0.3)
    used = sorted({leg.regulator for leg in robot.legs})
    for k in used:
        color = f"C{k - 1}"
        # the command in row i was sampled at the start t_{i-1} of its step
        ax_p.plot(result.time[:-1], result.commanded[1:, k - 1], "--", color=color, label=f"cmd {k}")
        ax_p.plot(result.time, result.applied[:, k - 1], "-", color=color, label=f"applied {k}")
    ax_p.set_xlabel("t (s)")
    ax_p.set_ylabel("pressure (real kPa)")
    ax_p.grid(alpha=0.3)
    ax_p.legend(ncols=len(used), fontsize="small")
    fig.savefig(path, dpi=120)


def write_paraview(directory: Path, robot: Robot, result: EpisodeResult, name: str = "crawl") -> None:
    """Write ``frames/frame_NNNNN.vtu`` per recorded frame and the index ``<name>.pvd``.

    Each ``.vtu`` holds all bodies' tetrahedra (global node numbering), the deformed
    positions (mm), point field ``"displacement"`` (mm, from rest) and cell field ``"body"``.
    """
    model = robot.model
    tets = np.concatenate([b.mesh.tets + off for b, off in zip(model.bodies, model.node_offsets)])
    body = np.concatenate([np.full(b.mesh.n_tets, i, np.int32) for i, b in enumerate(model.bodies)])
    rest = model.rest_state().x
    (directory / "frames").mkdir()
    entries = []
    for i, (t, x) in enumerate(zip(result.frame_times, result.frames)):
        rel = f"frames/frame_{i:05d}.vtu"
        mesh = meshio.Mesh(x.astype(np.float64), [("tetra", tets)],
                           point_data={"displacement": x - rest}, cell_data={"body": [body]})
        meshio.write(directory / rel, mesh, file_format="vtu")
        entries.append(f'    <DataSet timestep="{t:.6g}" group="" part="0" file={quoteattr(rel)}/>')
    (directory / f"{name}.pvd").write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "".join(e + "\n" for e in entries) + "  </Collection>\n</VTKFile>\n",
        encoding="utf-8",
    )


def write_results(out: str | os.PathLike, robot: Robot, gait, result: EpisodeResult,
                  calibration: PressureCalibration = PressureCalibration(), overwrite: bool = False,
                  video: bool = False, extra: Callable[[Path], None] | None = None,
                  animation: bool = False) -> Path:
    """Write all outputs (module docstring) into ``out`` atomically (:func:`staged_directory`).

    With ``animation``, also ``crawl.gif`` (:func:`softcrawl.robot.animation.write_animation`;
    left out if the episode recorded no frames); with ``video``, also
    ``crawl.mp4`` (:func:`softcrawl.robot.video.write_video`);
    ``extra(folder)`` writes a caller's own files into the same staged folder (e.g.
    ``softcrawl evaluate``'s ``evaluation.json``), so they are kept like the rest.

    If the disk fills up (or turns read-only) the staged folder keeps what was written and
    ``summary.json``, ``trajectory.npz`` / ``.csv`` and ``extra``'s files are saved into a
    :func:`rescue_directory` (the :class:`OutputWriteError` names both).

    Returns:
        ``out`` as a Path.

    Raises:
        OutputExistsError: ``out`` exists and ``overwrite`` is False.
        OutputWriteError: disk full / read-only (see above).
        VideoUnavailableError: ``video`` without pyvista / imageio-ffmpeg (nothing is written).
        OSError: on other write failures (nothing is left at ``out`` then).
    """
    info = json.dumps(summary(robot, gait, result, calibration), indent=2) + "\n"

    def essentials(folder: Path) -> None:
        (folder / "summary.json").write_text(info, encoding="utf-8")
        write_trajectory(folder, result)
        if extra is not None:
            extra(folder)

    with staged_directory(out, overwrite, rescue=essentials) as tmp:
        (tmp / "summary.json").write_text(info, encoding="utf-8")
        write_trajectory(tmp, result)
        if extra is not None:
            extra(tmp)
        plot_trajectory(tmp / "trajectory.png", robot, result)
        write_paraview(tmp, robot, result)
        if animation and len(result.frames):
            write_animation(tmp / "crawl.gif", robot, result)
        if video:
            from softcrawl.robot.video import write_video  # optional extra, heavy import

            write_video(tmp / "crawl.mp4", robot, result)
    return Path(out)
