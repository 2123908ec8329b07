"""Robot assembly, episodes and ``softcrawl simulate`` (coarse 12 mm leg meshes, short runs)."""

from __future__ import annotations

import json
import math

import meshio
import numpy as np
import pytest

import softcrawl.cli as cli
from softcrawl.design.space import BASELINE_DESIGN, InvalidDesignError
from softcrawl.fem.solver import SimulationDiverged, StepStats
from softcrawl.gaits import SineGait
from softcrawl.robot import NO_SETTLING, Episode, PressureRangeError, RobotConfig, build_robot, leg_transform, run_episode
from softcrawl.robot.assembly import FLOOR_CLEARANCE
from softcrawl.robot.output import CSV_COLUMNS, staged_directory

COARSE = RobotConfig(leg_mesh_size=12.0)


@pytest.fixture(scope="module")
def baseline():
    return build_robot(BASELINE_DESIGN, COARSE)


def test_baseline_model_structure(baseline):
    m = baseline.model
    assert len(m.bodies) == 5 and len(m.attachments) == 16 and m.n_channels == 3
    assert m.bodies[0].mass == 0.075 and [m.bodies[i].mass for i in baseline.leg_bodies] == [0.105] * 4
    assert m.total_mass == pytest.approx(0.495)
    assert [(g.slot, g.regulator, g.channel) for g in baseline.legs] == [(0, 1, 0), (3, 2, 1), (4, 2, 1), (7, 1, 0)]
    assert [m.bodies[g.body].cavities[0].channel for g in baseline.legs] == [0, 1, 1, 0]
    assert m.floor.friction == 1.2 and m.floor.contact_distance == 0.5
    assert baseline.regulator_channels == {1: 0, 2: 1, 3: 2}
    top = baseline.reward_position(m.rest_state().x)
    np.testing.assert_allclose(top[:2], 0.0, atol=1e-9)
    assert top[2] == pytest.approx(m.rest_state().x[m.body_slice(0), 2].max())
    ctrl = baseline.control([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(ctrl.pressures, [1.0, 2.0, 3.0])
    with pytest.raises(ValueError):
        baseline.control([1.0, 2.0])


def test_channels_fixed_for_any_design():
    r = build_robot("1,1,1,0,0,0,0,0", COARSE)  # only regulator 1 used
    assert r.model.n_channels == 3 and len(r.model.bodies) == 4
    with pytest.raises(InvalidDesignError):
        build_robot("1,0,0,0,0,0,0,0", COARSE)


def test_leg_transform():
    R, t = leg_transform(0.0)
    assert (R @ [52.0, 0, 0])[2] < 0  # outer tip dips down
    np.testing.assert_allclose(t, [100.228, 0, 9.459], atol=1e-3)
    R90, t90 = leg_transform(90.0)
    np.testing.assert_allclose(t90, [0, 100.228, 9.459], atol=1e-3)
    np.testing.assert_allclose(R90 @ [1.0, 0, 0], [0, math.cos(math.radians(15)), -math.sin(math.radians(15))],
                               atol=1e-12)


def test_placement_geometry(baseline):
    m = baseline.model
    x = m.rest_state().x
    for att in m.attachments:
        np.testing.assert_allclose(m.point_position(x, att.a), m.point_position(x, att.b), atol=1e-9)
    assert x[:, 2].min() == pytest.approx(FLOOR_CLEARANCE, abs=1e-9)
    for i in baseline.leg_bodies:
        body_x = x[m.body_slice(i)]
        tips = m.bodies[i].mesh.node_sets["tip"]
        assert body_x[tips, 2].min() == pytest.approx(body_x[:, 2].min(), abs=1e-9)  # tips are the lowest
        assert body_x[:, 2].min() == pytest.approx(FLOOR_CLEARANCE, abs=1e-9)
    # disk lifted by 2*52 sin15; the whole robot shifted so the tip corner (57.5, y, 0) sits at the clearance
    sin15 = math.sin(math.radians(15))
    disk_bottom = FLOOR_CLEARANCE + 2 * 52 * sin15 + 57.5 * sin15 - (52 * sin15 - 4)
    assert x[m.body_slice(0), 2].min() == pytest.approx(disk_bottom, abs=1e-9)


def test_settle_onto_floor(baseline):
    """0.5 s at zero pressure: no divergence, no penetration beyond the contact distance,
    and the floor carries the weight (loose check: total normal force within 5% of m g
    once the robot has come to rest; it still creeps slowly)."""
    ep = Episode(baseline, settling=NO_SETTLING)
    ep.reset()
    for _ in range(50):
        state = ep.step(np.zeros(3))
        assert state.x[:, 2].min() > -0.5
    weight = baseline.model.total_mass * 9800.0
    assert ep.solver.stats.normal_force == pytest.approx(weight, rel=0.05)
    assert state.t == pytest.approx(0.5)


class _FakeSolver:
    """Returns the state unchanged (time advanced); raises SimulationDiverged at call ``fail_at``."""

    def __init__(self, fail_at):
        self.calls, self.fail_at, self.stats = 0, fail_at, StepStats(n_contacts=7, factorizations=5)

    def step(self, state, control):
        self.calls += 1
        if self.calls == self.fail_at:
            raise SimulationDiverged("test", state.t)
        return type(state)(x=state.x + [0.1, 0, 0], v=state.v, t=state.t + 0.01)


def test_run_episode_records_and_divergence(baseline, monkeypatch):
    # settling takes a solver of its own (5 calm steps: the fake state never moves), the episode a fresh one
    monkeypatch.setattr(type(baseline), "make_solver", lambda self: _FakeSolver(fail_at=11))
    res = run_episode(baseline, SineGait(phase_deg=110), duration=1.0, record_every=5, progress=False)
    assert res.diverged and "test" in res.reason and res.steps == 10
    assert res.time.shape == (11,) and res.position.shape == (11, 3) and res.contacts[1] == 7
    assert res.reward_cm == pytest.approx(10 * 0.1 / 10)  # 10 steps of 0.1 mm, in cm
    np.testing.assert_allclose(res.commanded[1], SineGait(phase_deg=110).pressure_at(0.0))
    np.testing.assert_allclose(res.applied[1], np.minimum(res.commanded[1], 1.5))  # 150 kPa/s * 0.01 s
    assert res.frames.shape == (3, baseline.model.n_nodes, 3) and list(res.frame_times) == [0.0, 0.05, 0.1]
    assert res.settled == {"settle_steps": 5, "settle_seconds": 0.05, "rest_speed_mm_s": 0.0, "at_rest": True}


def test_run_episode_rejects_out_of_range_gait(baseline, monkeypatch):
    class Bad:
        def pressure_at(self, t):
            return np.array([95.0, 0.0, 0.0])

    monkeypatch.setattr(type(baseline), "make_solver", lambda self: _FakeSolver(fail_at=-1))
    with pytest.raises(PressureRangeError):
        run_episode(baseline, Bad(), duration=0.1, progress=False)


def test_staged_directory_cleans_up_on_error(tmp_path):
    with pytest.raises(RuntimeError):
        with staged_directory(tmp_path / "out") as tmp:
            (tmp / "summary.json").write_text("{}")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def _simulate(monkeypatch, *args):
    assert "softcrawl.cli.simulate" in cli.SUBCOMMANDS
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("softcrawl.cli.simulate",))  # isolate from other subcommands
    return cli.main(["simulate", "--model", "full", "--mesh-size", "12", "--no-progress", *map(str, args)])


def test_cli_simulate_writes_outputs(tmp_path, monkeypatch, capsys):
    out = tmp_path / "runs" / "best"
    rc = _simulate(monkeypatch, "--design", "1,0,0,2,2,0,0,0", "--gait", "paper-best", "--duration", 1,
                   "--frames-every", 50, "--out", out)
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [
        ".softcrawl-output", "crawl.gif", "crawl.pvd", "frames", "summary.json", "trajectory.csv", "trajectory.npz",
        "trajectory.png"]
    assert [p.name for p in out.parent.iterdir()] == ["best"]  # no temporary leftovers
    s = json.loads((out / "summary.json").read_text())
    assert s["design"] == [1, 0, 0, 2, 2, 0, 0, 0] and s["steps"] == 100 and s["model"] == "full"
    assert s["diverged"] is False and math.isfinite(s["reward_cm"]) and s["mesh"]["leg_mesh_size"] == 12.0
    assert s["gait"]["type"] == "ActionSequence" and s["solver"]["factorizations"] > 0
    rows = (out / "trajectory.csv").read_text().splitlines()
    assert rows[0].split(",") == list(CSV_COLUMNS) and len(rows) == 102
    npz = np.load(out / "trajectory.npz")
    assert npz["position"].shape == (101, 3)
    np.testing.assert_allclose(npz["commanded"][1], [0, 90, 0])  # paper gait: rear legs first
    assert (out / "crawl.pvd").read_text().count("<DataSet") == 3
    grid = meshio.read(out / "frames" / "frame_00002.vtu")
    assert grid.points.shape == (s["mesh"]["nodes"], 3)
    assert set(grid.cell_data["body"][0]) == {0, 1, 2, 3} and "displacement" in grid.point_data
    # an existing output is refused without --overwrite
    assert _simulate(monkeypatch, "--duration", 0.01, "--out", out) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["design", "csv", "range", "missing"])
def test_cli_simulate_errors_leave_no_output(tmp_path, monkeypatch, capsys, case):
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text({"csv": "p1,p2,p3\n10,20\n", "range": "10,20,30\n10,120,0\n"}.get(case, ""))
    extra = {
        "design": ["--design", "1,0,0,0,0,0,0,0"],
        "csv": ["--actions", bad_csv],
        "range": ["--actions", bad_csv],
        "missing": ["--actions", tmp_path / "nope.csv"],
    }[case]
    out = tmp_path / "runs" / "x"
    assert _simulate(monkeypatch, "--duration", 0.05, "--out", out, *extra) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("softcrawl simulate: error:") and "\n" not in err
    assert not out.exists() and not (tmp_path / "runs").exists()


def test_attachment_patches():
    """Each attachment point averages the corner node's one-ring ("node": the corner alone)."""
    from softcrawl.robot.assembly import RobotConfig, build_robot

    patched = build_robot("1,0,0,2,2,0,0,0", RobotConfig(leg_mesh_size=12.0, attachment_patch="ring"))
    single = build_robot("1,0,0,2,2,0,0,0", RobotConfig(leg_mesh_size=12.0, attachment_patch="node"))
    assert all(len(a.a.nodes) > 1 and np.isclose(a.a.weights.sum(), 1.0) for a in patched.model.attachments)
    assert all(len(a.a.nodes) == 1 for a in single.model.attachments)
    with pytest.raises(ValueError, match="attachment_patch"):
        RobotConfig(attachment_patch="glue")


@pytest.mark.slow
def test_full_pressure_at_4mm_does_not_invert_elements():
    """Regression: single-node attachments crushed the corner element of a rear leg at 4 mm
    (t = 0.85 s of the paper's gait, 347 sim kPa): reported as divergence."""
    from softcrawl.gaits import paper_best_gait
    from softcrawl.robot.assembly import RobotConfig, build_robot
    from softcrawl.robot.episode import run_episode

    robot = build_robot("1,0,0,2,2,0,0,0", RobotConfig(leg_mesh_size=4.0, refactor_every=5))
    result = run_episode(robot, paper_best_gait(), duration=1.2, record_every=None, progress=False)
    assert not result.diverged, result.reason
