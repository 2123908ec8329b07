"""``softcrawl sweep-phase`` (phase sweep of the baseline) and ``softcrawl simulate --video``
(coarse 12 mm legs, 0.2 s episodes)."""

from __future__ import annotations

import csv
import json
import math
import sys

import pytest

import softcrawl.cli as cli
import softcrawl.robot.sweep as sweep
from softcrawl.design.space import BASELINE_DESIGN
from softcrawl.robot import RobotConfig
from softcrawl.robot.output import OutputExistsError
from softcrawl.robot.sweep import PhaseResult, SweepSettingsMismatch, parse_phases, run_sweep

COARSE = RobotConfig(leg_mesh_size=12.0)
DURATION = 0.2
PHASES = (0.0, 90.0, 180.0)


def _main(monkeypatch, module, *args):
    monkeypatch.setattr(cli, "SUBCOMMANDS", (module,))  # isolate from other subcommands
    return cli.main([str(a) for a in args])


def _fake_run_phase(calls, interrupt_at=None):
    """Stand-in for :func:`run_phase` (in-process sweeps): reward = phase / 100 cm; records its calls."""

    def run(design, config, phase, duration, calibration=None, space=None):  # run_phase's arguments
        if phase == interrupt_at:
            raise KeyboardInterrupt
        calls.append(phase)
        diverged = phase == 0.0
        return PhaseResult(phase, math.nan if diverged else phase / 100, -0.5 if diverged else phase / 100,
                           diverged, "fake divergence" if diverged else "", 7 if diverged else 20, 0.5)

    return run


def _interrupted(monkeypatch, out, interrupt_at=90.0, duration=DURATION):
    """Run an in-process sweep that is interrupted at ``interrupt_at``; returns the phases it finished."""
    calls = []
    monkeypatch.setattr(sweep, "run_phase", _fake_run_phase(calls, interrupt_at))
    with pytest.raises(KeyboardInterrupt):
        run_sweep(out, PHASES, BASELINE_DESIGN, COARSE, duration, workers=1, progress=False)
    monkeypatch.undo()
    return calls


def test_parse_phases():
    p = parse_phases("0:180:10")
    assert len(p) == 19 and p[0] == 0.0 and p[-1] == 180.0 and p[11] == 110.0
    assert parse_phases("0:180:20")[-1] == 180.0 and parse_phases("0:175:50") == (0.0, 50.0, 100.0, 150.0)
    assert parse_phases("110") == (110.0,) and parse_phases("0, 90,45") == (0.0, 90.0, 45.0)
    for bad in ("0:180", "0:180:0", "180:0:10", "a,b", "0,0", "nan", ""):
        with pytest.raises(ValueError):
            parse_phases(bad)


def test_sweep_outputs_and_resume_on_workers(tmp_path, monkeypatch, capsys):
    """An interrupted sweep left phase 0 (a fake diverged episode) behind; the same command on 2
    worker processes reuses it and simulates only 90 and 180 for real."""
    out = tmp_path / "runs" / "sweep"
    work = tmp_path / "runs" / "sweep.partial"
    assert _interrupted(monkeypatch, out) == [0.0]
    assert not out.exists() and [p.name for p in (work / "partial").iterdir()] == ["phase_0.0.json"]

    rc = _main(monkeypatch, "softcrawl.cli.sweep", "sweep-phase", "--out", out, "--phases", "0:180:90",
               "--duration", DURATION, "--model", "full", "--mesh-size", 12, "--workers", 2, "--no-progress")
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert sorted(p.name for p in out.iterdir()) == [".softcrawl-output", "reward_vs_phase.png", "sweep.csv",
                                                    "sweep.json"]
    assert [p.name for p in out.parent.iterdir()] == ["sweep"]  # work dir and temporaries gone

    s = json.loads((out / "sweep.json").read_text())
    rows = {r["phase_deg"]: r for r in s["phases"]}
    assert [r["phase_deg"] for r in s["phases"]] == list(PHASES) and s["reused_phases"] == [0.0]
    assert rows[0.0]["reused"] and rows[0.0]["diverged"] and rows[0.0]["reward_cm"] is None  # not re-run
    assert rows[0.0]["reason"] == "fake divergence"
    for p in (90.0, 180.0):  # simulated: 20 steps of 0.01 s, finite reward
        assert not rows[p]["reused"] and not rows[p]["diverged"] and rows[p]["steps"] == 20
        assert math.isfinite(rows[p]["reward_cm"]) and rows[p]["wall_seconds"] > 0
    best = max((90.0, 180.0), key=lambda p: rows[p]["reward_cm"])
    assert s["best"] == {"phase_deg": best, "reward_cm": rows[best]["reward_cm"]}
    assert s["workers"] == 2 and s["paper_best_phase_deg"] == 110.0 and s["wall_seconds"] > 0
    assert s["settings"]["duration_s"] == DURATION and s["settings"]["config"]["leg_mesh_size"] == 12.0
    assert s["settings"]["design"] == list(BASELINE_DESIGN) and "softcrawl_version" in s

    with (out / "sweep.csv").open() as f:
        table = list(csv.DictReader(f))
    assert [r["phase_deg"] for r in table] == ["0", "90", "180"] and list(table[0]) == list(sweep.CSV_COLUMNS)
    assert table[0]["reward_cm"] == "" and table[0]["diverged"] == "1"
    assert float(table[2]["reward_cm"]) == pytest.approx(rows[180.0]["reward_cm"], rel=1e-5)

    lines = captured.out.splitlines()
    line = {float(ln.split()[0]): ln for ln in lines[1:4]}
    assert "DIVERGED" in line[0.0] and "after 7 steps: fake divergence" in line[0.0]
    assert "<- best" in line[best] and sum("<- best" in ln for ln in lines) == 1
    assert f"{rows[best]['reward_cm']:+.3f}" in line[best]
    assert lines[4] == f"best: {best:g} deg, {rows[best]['reward_cm']:+.3f} cm"
    assert "1 reused" in lines[5] and "2 worker(s)" in lines[5]

    # an existing output is refused (before any work) unless --overwrite
    rc = _main(monkeypatch, "softcrawl.cli.sweep", "sweep-phase", "--out", out, "--phases", "0", "--no-progress")
    assert rc == 2 and "already exists" in capsys.readouterr().err


def test_sweep_passes_the_model_arguments_to_its_config(tmp_path, monkeypatch):
    """Regression: ``--reduced-disk`` (a shared model argument) was accepted by sweep-phase but
    left out of the robot config it ran."""
    from softcrawl.cli import sweep as sweep_cli

    seen = []

    def fake(out, phases, design, config, *a, **k):
        seen.append(config)
        raise KeyboardInterrupt

    monkeypatch.setattr(sweep_cli, "run_sweep", fake)
    rc = _main(monkeypatch, "softcrawl.cli.sweep", "sweep-phase", "--out", tmp_path / "s", "--phases", "0",
               "--reduced-disk", "corotational", "--no-progress")
    assert rc == 130 and seen[0].reduced_disk == "corotational" and seen[0].model == "reduced"


def test_resume_runs_only_unfinished_phases(tmp_path, monkeypatch):
    out = tmp_path / "sweep"
    assert _interrupted(monkeypatch, out) == [0.0]
    calls = []
    monkeypatch.setattr(sweep, "run_phase", _fake_run_phase(calls))
    res = run_sweep(out, PHASES, BASELINE_DESIGN, COARSE, DURATION, workers=1, progress=False)
    assert calls == [90.0, 180.0]  # phase 0 was not re-run
    assert [r.phase_deg for r in res.phases] == list(PHASES) and [r.reused for r in res.phases] == [True, False, False]
    assert res.best.phase_deg == 180.0 and res.best.reward_cm == 1.8  # the diverged phase 0 is never best
    assert "DIVERGED" in sweep.format_table(res).splitlines()[1]
    assert out.is_dir() and not (tmp_path / "sweep.partial").exists()


def test_mismatched_settings_refused(tmp_path, monkeypatch, capsys):
    out = tmp_path / "sweep"
    work = tmp_path / "sweep.partial"
    _interrupted(monkeypatch, out, duration=DURATION)
    monkeypatch.setattr(sweep, "run_phase", _fake_run_phase([], interrupt_at=0.0))  # must not be reached
    with pytest.raises(SweepSettingsMismatch, match=r"duration_s: 0\.2 there, 0\.3 now"):
        run_sweep(out, PHASES, BASELINE_DESIGN, COARSE, 0.3, workers=1, progress=False)
    rc = _main(monkeypatch, "softcrawl.cli.sweep", "sweep-phase", "--out", out, "--phases", "0:180:90",
               "--duration", DURATION, "--model", "full", "--mesh-size", 8, "--no-progress")
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "config.leg_mesh_size: 12.0 there, 8.0 now" in err and "delete" in err and "\n" not in err
    assert not out.exists() and (work / "partial" / "phase_0.0.json").exists()  # the partial sweep is kept


def test_existing_output_refused_before_work(tmp_path, monkeypatch):
    out = tmp_path / "sweep"
    out.mkdir()
    monkeypatch.setattr(sweep, "run_phase", _fake_run_phase([], interrupt_at=0.0))
    with pytest.raises(OutputExistsError):
        run_sweep(out, PHASES, BASELINE_DESIGN, COARSE, DURATION, workers=1, progress=False)
    assert not (tmp_path / "sweep.partial").exists()


def test_video_fails_before_simulating_without_pyvista(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as simulate

    monkeypatch.setitem(sys.modules, "pyvista", None)  # import pyvista -> ImportError
    monkeypatch.setattr(simulate, "build_robot", lambda *a, **k: pytest.fail("simulated without pyvista"))
    out = tmp_path / "runs" / "v"
    assert _main(monkeypatch, "softcrawl.cli.simulate", "simulate", "--video", "--out", out, "--no-progress") == 2
    err = capsys.readouterr().err.strip()
    assert "pip install softcrawl[video]" in err and "\n" not in err
    assert not (tmp_path / "runs").exists()


def test_simulate_video_renders(tmp_path, monkeypatch, capsys):
    pytest.importorskip("pyvista")
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    from softcrawl.robot.video import VideoUnavailableError, check_video_support

    try:
        check_video_support()
    except VideoUnavailableError as exc:
        pytest.skip(str(exc))
    out = tmp_path / "v"
    rc = _main(monkeypatch, "softcrawl.cli.simulate", "simulate", "--video", "--out", out, "--no-progress",
               "--mesh-size", 12, "--duration", 0.02, "--frames-every", 1)
    assert rc == 0, capsys.readouterr().err
    video = out / "crawl.mp4"
    assert video.stat().st_size > 0
    assert imageio_ffmpeg.count_frames_and_secs(str(video))[0] == 3  # t = 0, 0.01, 0.02 s
