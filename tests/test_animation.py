"""The animated GIF of an episode (:mod:`softcrawl.robot.animation`): what it draws, its frames,
its errors, headless rendering, and where ``simulate``, ``evaluate`` and the report write it.

Most tests draw a synthetic episode of a coarse robot (12 mm legs, nothing simulated): the rest
positions translated along +x, with made-up regulator pressures.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from softcrawl.gaits.pressure import P_MAX_KPA
from softcrawl.geometry.mesh import boundary_triangles
from softcrawl.robot.animation import frame_indices, robot_surface, write_animation
from softcrawl.robot.assembly import RobotConfig, build_robot
from softcrawl.robot.episode import EpisodeResult

DESIGN = (1, 0, 0, 2, 2, 0, 0, 1)
SMALL = (160, 120)


@pytest.fixture(scope="module")
def robot():
    return build_robot(DESIGN, RobotConfig(leg_mesh_size=12.0, disk_mesh_size=25.0))


def episode(robot, k: int = 7, step_mm: float = 2.0, pressure_kpa: float | None = None) -> EpisodeResult:
    """``k`` frames 0.1 s apart, moving ``step_mm`` along +x per frame; applied pressures ramp
    from 0 to 90 kPa (or stay at ``pressure_kpa``), one row per 0.05 s."""
    rest = robot.model.rest_state().x
    times = 0.1 * np.arange(k)
    frames = np.stack([rest + [step_mm * i, 0.0, 0.0] for i in range(k)]).astype(np.float32)
    t = np.arange(2 * k - 1) * 0.05
    ramp = np.linspace(0.0, P_MAX_KPA, len(t)) if pressure_kpa is None else np.full(len(t), pressure_kpa)
    applied = np.column_stack([ramp] * 3)
    return EpisodeResult(time=t, position=np.zeros((len(t), 3)), commanded=applied, applied=applied,
                         contacts=np.zeros(len(t), np.int64), contact_sweeps=np.zeros(len(t), np.int64),
                         factorizations=0, frame_times=times, frames=frames, reward_cm=0.0, steps=len(t) - 1,
                         sim_seconds=float(t[-1]), wall_seconds=1.0)


def _frames(path: Path) -> list[np.ndarray]:
    """The GIF's frames as ``(height, width, 3)`` float RGB, without their top quarter (the
    caption and the pressure labels, which are coloured too)."""
    with Image.open(path) as im:
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append(np.asarray(im.convert("RGB"), dtype=float)[im.size[1] // 4:])
    return out


def test_surface_is_each_body_outer_skin_with_its_regulator(robot):
    s = robot_surface(robot)
    model = robot.model
    for i, body in enumerate(model.bodies):
        sl = model.body_slice(i)
        mine = (s.triangles >= sl.start).all(axis=1) & (s.triangles < sl.stop).all(axis=1)
        outer = body.mesh.surfaces["boundary"]
        assert mine.sum() == len(outer)
        # the outer skin only: a leg's cavity walls are tet boundary faces but not drawn
        assert len(outer) < len(boundary_triangles(body.mesh.tets)) or i == robot.disk_body
        regs = {leg.body: leg.regulator for leg in robot.legs}
        assert set(s.regulator[mine]) == {regs.get(i, 0)}


def test_frames_are_subsampled_evenly_from_first_to_last():
    assert frame_indices(101, 60)[[0, -1]].tolist() == [0, 100] and len(frame_indices(101, 60)) == 60
    assert np.ptp(np.diff(frame_indices(101, 60))) <= 1
    assert frame_indices(7, 60).tolist() == list(range(7))
    assert frame_indices(1, 1).tolist() == [0]


def test_short_trajectory_renders_a_gif_of_the_asked_frames_and_size(robot, tmp_path):
    path = tmp_path / "crawl.gif"
    assert write_animation(path, robot, episode(robot), fps=10, max_frames=4, size=SMALL) == 4
    with Image.open(path) as im:
        assert im.format == "GIF" and im.size == SMALL and im.n_frames == 4
        assert im.info["duration"] == 100 and im.info["loop"] == 0  # 10 fps, loops forever
    # the robot is drawn: disk grey and both regulators' colours (blue, orange) in sight
    img = _frames(path)[0]
    grey = np.abs(img - img.mean(axis=2, keepdims=True)).max(axis=2) < 8
    blue = (img[..., 2] > img[..., 0] + 40)
    orange = (img[..., 0] > img[..., 2] + 40)
    assert (grey & (img.mean(axis=2) < 200)).sum() > 200 and blue.sum() > 100 and orange.sum() > 100


def test_legs_turn_from_pale_to_full_colour_with_pressure(robot, tmp_path):
    """At 0 kPa the legs are a pale tint, at 90 kPa their full colour: the drawn robot is more
    saturated (max - min channel, over non-background pixels) at full pressure."""

    def saturation(kpa):
        write_animation(tmp_path / "p.gif", robot, episode(robot, k=1, pressure_kpa=kpa), size=SMALL)
        img = _frames(tmp_path / "p.gif")[0]
        sat = img.max(axis=2) - img.min(axis=2)
        return sat[sat > 20].mean(), (sat > 60).sum()

    (pale, n_pale), (full, n_full) = saturation(0.0), saturation(P_MAX_KPA)
    assert full > pale + 30 and n_full > 2 * n_pale


def test_camera_follows_the_robot(robot, tmp_path):
    """The robot moves 120 mm along +x over the episode; its drawing stays put in the image
    (to a few pixels) while the world-fixed floor grid moves under it."""
    path = tmp_path / "move.gif"
    write_animation(path, robot, episode(robot, k=2, step_mm=120.0, pressure_kpa=P_MAX_KPA), size=SMALL)
    first, last = _frames(path)
    robot_px = [np.argwhere(np.abs(f[..., 0] - f[..., 2]) > 40).mean(axis=0) for f in (first, last)]
    assert np.abs(robot_px[0] - robot_px[1]).max() < 3


@pytest.mark.parametrize("change, message", [
    (dict(frames=np.zeros((0, 1, 3), np.float32), frame_times=np.zeros(0)), "recorded no frames"),
    (dict(frames=np.zeros((2, 5, 3), np.float32), frame_times=np.zeros(2)), "must have shape"),
])
def test_bad_episodes_are_refused_before_drawing(robot, tmp_path, change, message):
    bad = dataclasses.replace(episode(robot), **change)
    with pytest.raises(ValueError, match=message):
        write_animation(tmp_path / "x.gif", robot, bad)
    assert not (tmp_path / "x.gif").exists()


def test_non_finite_positions_are_refused_naming_the_frame(robot, tmp_path):
    ep = episode(robot)
    ep.frames[3, 10, 2] = np.nan
    with pytest.raises(ValueError, match=r"frame 3 \(t = 0.3 s\) has non-finite"):
        write_animation(tmp_path / "x.gif", robot, ep)
    ep.frames[3, 10, 2] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        write_animation(tmp_path / "x.gif", robot, ep)
    assert not (tmp_path / "x.gif").exists()


@pytest.mark.parametrize("kw, message", [
    (dict(max_frames=0), "max_frames must be an integer >= 1"),
    (dict(max_frames=2.5), "max_frames must be an integer >= 1"),
    (dict(fps=0), r"fps must be in \(0, 100\]"),
    (dict(fps=float("nan")), "fps must be"),
    (dict(size=(10, 120)), "size must be"),
    (dict(size=(160,)), "size must be"),
    (dict(size=160), "size must be"),
])
def test_bad_arguments_are_refused_before_drawing(robot, tmp_path, kw, message):
    with pytest.raises(ValueError, match=message):
        write_animation(tmp_path / "x.gif", robot, episode(robot), **kw)
    assert not (tmp_path / "x.gif").exists()


def test_renders_headless_without_pyplot(tmp_path):
    """No display, ``MPLBACKEND=Agg``: the GIF is drawn on matplotlib's Agg canvas and pyplot
    (which would pick a GUI backend) is never imported."""
    script = (
        "import sys, numpy as np\n"
        "sys.path.insert(0, sys.argv[2])\n"
        "from test_animation import episode\n"
        "from softcrawl.robot.animation import write_animation\n"
        "from softcrawl.robot.assembly import RobotConfig, build_robot\n"
        "robot = build_robot((1, 0, 0, 2, 2, 0, 0, 1), RobotConfig(leg_mesh_size=12.0, disk_mesh_size=25.0))\n"
        "print(write_animation(sys.argv[1], robot, episode(robot, k=2), size=(96, 64)))\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MPLBACKEND"] = "Agg"
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).parents[1]), env.get("PYTHONPATH", "")])
    out = tmp_path / "h.gif"
    proc = subprocess.run([sys.executable, "-c", script, str(out), str(Path(__file__).parent)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split()[-1] == "2"
    with Image.open(out) as im:
        assert im.n_frames == 2 and im.size == (96, 64)


def _gif_frames(path: Path) -> int:
    with Image.open(path) as im:
        assert im.format == "GIF"
        return im.n_frames


def test_simulate_writes_the_animation_unless_told_not_to(tmp_path, capsys):
    from softcrawl.cli import main

    args = ["simulate", "--disk-mesh-size", "25", "--duration", "0.03", "--frames-every", "1", "--no-progress", "--out"]
    assert main([*args, str(tmp_path / "a")]) == 0, capsys.readouterr().err
    assert _gif_frames(tmp_path / "a" / "crawl.gif") == 4  # t = 0, 0.01, 0.02, 0.03 s
    assert main([*args, str(tmp_path / "b"), "--no-animation"]) == 0, capsys.readouterr().err
    assert (tmp_path / "b" / "trajectory.csv").exists() and not (tmp_path / "b" / "crawl.gif").exists()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished smoke training run (40 steps, one checkpoint; 0.4 s episodes at 0.01 s)."""
    from softcrawl.codesign.config import override, preset
    from softcrawl.codesign.training import train

    path = tmp_path_factory.mktemp("anim") / "run"
    train(path, override(preset("smoke"), ["total_steps=40", "checkpoint_every=40", "snapshot_every=40"]),
          progress=False)
    return path


def test_report_shows_the_best_design_crawling(run):
    from softcrawl.codesign.report import write_report

    report = write_report(run, baseline_phases=())
    gif = report / "best_design" / "crawl.gif"
    assert _gif_frames(gif) == 5  # a frame every 10 steps of 0.01 s over 0.4 s
    assert "![best design crawling](best_design/crawl.gif)" in (report / "summary.md").read_text()


def test_evaluate_writes_the_animation_unless_told_not_to(run, tmp_path, capsys):
    from softcrawl.cli import main

    args = ["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--frames-every", "20", "--no-progress", "--out"]
    assert main([*args, str(tmp_path / "a")]) == 0, capsys.readouterr().err
    assert _gif_frames(tmp_path / "a" / "crawl.gif") == 3  # t = 0, 0.2, 0.4 s
    assert main([*args, str(tmp_path / "b"), "--no-animation"]) == 0, capsys.readouterr().err
    assert (tmp_path / "b" / "evaluation.json").exists() and not (tmp_path / "b" / "crawl.gif").exists()


def test_evaluate_randomize_refuses_the_animation_flags(run, tmp_path, capsys):
    """``--randomize N`` writes a reward distribution, no trajectory: an animation flag would be
    ignored, so it is a one-line error before any episode runs."""
    from softcrawl.cli import main

    for flag in ("--animation", "--no-animation"):
        rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--randomize", "2", flag,
                   "--out", str(tmp_path / "r"), "--no-progress"])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and "writes no trajectory to animate" in err and "\n" not in err
        assert not (tmp_path / "r").exists()
