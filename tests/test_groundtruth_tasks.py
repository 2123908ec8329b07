"""The ground truth and the regret on another design space and another task: a tiny ground truth of
the 2-regulator ``hex6`` space through ``softcrawl groundtruth --space hex6``; a tiny ``turning``
ground truth whose best reward is recomputed independently (:func:`softcrawl.tasks.baselines.turned_degrees`
on a robot built here); ``regret`` refusing a run of another task; folders saved before tasks
existed read as ``forward`` with their numbers unchanged."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import softcrawl.codesign.groundtruth_regret as rg
from groundtruth_helpers import DESIGNS, fake_task
from softcrawl.cli import main as cli_main
from softcrawl.codesign.groundtruth import (
    DesignEvaluator,
    GroundTruthConfig,
    PeriodicGait,
    load_groundtruth,
    load_results,
    parse_designs,
    read_config,
    gt_robot,
    run_groundtruth,
)
from softcrawl.codesign.groundtruth.optimize import episode_return
from softcrawl.codesign.groundtruth.store import folder_task
from softcrawl.design.resolve import resolve_space
from softcrawl.robot.assembly import build_robot
from softcrawl.tasks import Forward, Heading, make_task
from softcrawl.tasks.baselines import TURNING_BASELINE_DESIGN, turned_degrees, turning_gait

#: The smallest search: one cycle length, 3 screening episodes of 0.5 s, one finalist (step and
#: smooth finals of ``--duration``), the demo's coarse disk, no expert-baseline sweep.
TINY = ["--cycles", "2", "--evals-per-cycle", "3", "--finalists", "1", "--screen-duration", "0.5",
        "--disk-mesh-size", "25", "--baseline-phases", "none", "--executor", "serial", "--no-progress"]
SHIPPED = Path(__file__).resolve().parents[1] / "benchmarks" / "groundtruth" / "three-legged"
DATA = Path(__file__).resolve().parent / "data"
L1 = (1, 0, 0, 2, 2, 0, 0, 0)


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path / "cache"))


def test_hex6_groundtruth_through_the_cli(tmp_path, cache, capsys):
    hex6 = resolve_space("hex6")
    design = parse_designs("2", hex6)[0]
    out = tmp_path / "gt"
    assert cli_main(["groundtruth", "--out", str(out), "--space", "hex6", "--duration", "1.0",
                     "--designs", ",".join(map(str, design)) + ";", *TINY]) == 0
    res = load_results(out)
    assert list(res) == [design]
    r = res[design]
    assert r.evaluations == 5 and r.full_evaluations == 2 and math.isfinite(r.reward_cm)
    gait = PeriodicGait.from_dict(r.gait)
    assert hex6.n_regulators == 2  # the space's regulators, not the paper's 3
    assert gait.pressure_at(0.0).shape == (2,)
    assert read_config(out).design_space() == hex6 and (out / "space.toml").exists()
    assert not (out / "references.json").exists()  # the references are the paper space's designs
    # regression: the summary named the folder's space file by this machine's absolute path
    assert json.loads((out / "summary.json").read_text())["config"]["space"] == "space.toml"
    # the row's reward is the CPU engine's episode of its gait, recomputed here
    ev = DesignEvaluator(design, read_config(out))
    assert ev(gait, 1.0)[0] == pytest.approx(r.reward_cm, abs=1e-9)
    assert "1 of 1 designs done" in capsys.readouterr().out


def test_turning_groundtruth_rewards_the_yaw(tmp_path, cache, capsys):
    out = tmp_path / "gt"
    assert cli_main(["groundtruth", "--out", str(out), "--task", "turning", "--duration", "2.0",
                     "--designs", "1,0,0,2,2,0,0,0", *TINY, "--baseline-phases", "90"]) == 0
    cfg = read_config(out)
    assert cfg.task == "turning" and folder_task(out) == make_task("turning")
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert "reward_deg" in rows[0] and "reward_cm" not in rows[0]  # keyed in the task's unit
    summary = json.loads((out / "summary.json").read_text())
    assert summary["task"] == {"name": "turning", "friction": None, "vent_s": 5.0, "unit": "deg"}
    assert summary["best"][0]["reward_deg"] == rows[0]["reward_deg"]
    assert "turning baseline (90 deg lag)" in capsys.readouterr().out
    # independent recomputation: the disk's yaw sampled every second, wrapped increments summed,
    # scored at rest after the task's 5 s of venting
    robot = build_robot(L1, cfg.robot_config())
    turned, diverged = turned_degrees(robot, PeriodicGait.from_dict(rows[0]["gait"]), 2.0, sample_every=1.0,
                                      vent_seconds=5.0)
    assert not diverged and math.isfinite(turned)
    assert rows[0]["reward_deg"] == pytest.approx(turned, abs=1e-9)
    # the references: the turning task's hand-made baseline, not the forward ones, in degrees
    refs = json.loads((out / "references.json").read_text())
    assert set(refs) == {"turning_baseline"} and refs["turning_baseline"]["best_phase_deg"] == 90.0
    base = build_robot(TURNING_BASELINE_DESIGN, cfg.robot_config())
    turned, _ = turned_degrees(base, turning_gait(90.0), 2.0, sample_every=1.0, vent_seconds=5.0)
    assert refs["turning_baseline"]["reward_deg"] == pytest.approx(turned, abs=1e-9)
    assert summary["designs_beating_turning_baseline"] == int(rows[0]["reward_deg"] > turned)


@dataclass(frozen=True)
class _AtOnce(Heading):
    """Heading's reward (+x crawl, cm) whose goal is reached at once (the first sample)."""

    def reached(self, episode, origin) -> bool:
        return True


def test_episode_return_ends_when_the_goal_is_reached(cache):
    """An episode ends at the first sample where its task's goal is reached: its return is the
    first action's, whatever the episode's length; a task whose goal is never reached scores
    the whole episode (its +x crawl: run_episode's reward, recomputed here)."""
    from softcrawl.robot.episode import run_episode

    robot = build_robot(L1, gt_robot(disk_mesh_size=25.0))
    gait = PeriodicGait.paper_cycle()
    first, _ = episode_return(_AtOnce(), robot, gait, 1.0, 1.0)
    whole, div = episode_return(make_task("heading"), robot, gait, 3.0, 1.0)
    assert not div and episode_return(_AtOnce(), robot, gait, 3.0, 1.0)[0] == first
    assert first == pytest.approx(episode_return(make_task("heading"), robot, gait, 1.0, 1.0)[0], abs=1e-12)
    assert whole == pytest.approx(run_episode(robot, gait, 3.0, record_every=None, progress=False).reward_cm,
                                  abs=1e-9)
    assert abs(whole - first) > 1e-3  # the paper's cycle keeps crawling after its first second


def test_friction_of_the_task_is_the_robots_floor(cache):
    cfg = GroundTruthConfig(task={"name": "forward", "friction": 0.3})
    ev = DesignEvaluator(L1, cfg)
    assert ev.robot.config.friction == 0.3
    assert DesignEvaluator(L1, GroundTruthConfig()).robot.config.friction == 1.2  # the default floor


def _turning_folder(path: Path) -> Path:
    """A finished turning ground truth of :data:`DESIGNS` written by a fake worker (no simulation)."""
    run_groundtruth(DESIGNS, path, GroundTruthConfig(baseline_phases=(), task="turning"), executor="serial",
                    task=fake_task, progress=False, refs=False)
    return path


def test_regret_refuses_another_task_and_speaks_degrees(tmp_path, monkeypatch, capsys):
    gt = _turning_folder(tmp_path / "gt")
    monkeypatch.setattr(rg, "run_choice", lambda run: {"design": DESIGNS[0], "prob": 0.9, "latest_cm": 1.0,
                                                       "episodes": 7})
    monkeypatch.setattr(rg, "run_settings", lambda run: rg.gt_settings(read_config(gt)))
    # a forward run (an older run without a task is one) against a turning ground truth
    monkeypatch.setattr(rg, "run_task", lambda run: Forward())
    out = tmp_path / "regret.json"
    assert cli_main(["regret", "RUN", "--groundtruth", str(gt), "--no-policy", "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "different tasks" in err[0] and "turning" in err[0] and "forward" in err[0]
    assert not out.exists()
    # a turning run: the numbers in degrees
    monkeypatch.setattr(rg, "run_task", lambda run: make_task("turning"))
    r = rg.compute_regret("RUN", gt, policy=False)
    rewards = {d: fake_task(d, None)["reward_cm"] for d in DESIGNS}
    assert r["placement"]["regret_deg"] == pytest.approx(max(rewards.values()) - rewards[DESIGNS[0]])
    assert r["task"]["unit"] == "deg" and "reward_cm" not in r["placement"]
    assert "deg" in "\n".join(rg.regret_markdown(r))
    # the same task with other settings is another task
    monkeypatch.setattr(rg, "run_task", lambda run: make_task("turning", friction=0.5))
    with pytest.raises(ValueError, match="different tasks"):
        rg.compute_regret("RUN", gt, policy=False)


def test_shipped_groundtruth_reads_as_forward_and_a_format_1_folder_too(tmp_path):
    """The shipped ground truth records its task (``forward``); a folder written before tasks
    existed (the former shipped table's ``config.json``, format 1, with rows of today's) reads as
    ``forward`` in cm, its rows' numbers to the bit."""
    cfg, res, _ = load_groundtruth(SHIPPED)
    assert json.loads((SHIPPED / "config.json").read_text())["config"]["task"] == "forward"
    assert cfg.task_spec() == Forward() and folder_task(SHIPPED).unit == "cm"
    old = tmp_path / "old"
    old.mkdir()
    (old / "config.json").write_text((DATA / "groundtruth_config_v1.json").read_text())
    lines = (SHIPPED / "results.jsonl").read_text().splitlines(keepends=True)[:5]
    (old / "results.jsonl").write_text("".join(lines))
    assert "task" not in json.loads((old / "config.json").read_text())["config"]
    cfg, res, _ = load_groundtruth(old)
    assert cfg.task_spec() == Forward() and folder_task(old).unit == "cm"
    raw = {tuple(json.loads(line)["design"]): json.loads(line)["reward_cm"] for line in lines}
    assert {d: r.reward_cm for d, r in res.items()} == raw  # the file's numbers, to the bit
    p = rg.place_design(max(raw, key=raw.get), old, res)
    assert p["rank"] == 1 and p["regret_cm"] == 0.0 and p["of"] == 5


def test_a_task_the_jax_engine_cannot_score_is_refused():
    with pytest.raises(ValueError, match='engine "jax" does not run task .turning.'):
        GroundTruthConfig(task="turning", engine="jax").validate()
    with pytest.raises(ValueError, match="task: unknown task"):
        GroundTruthConfig(task="fly").validate()


@pytest.mark.slow
def test_hex6_jax_groundtruth_rows_are_the_cpu_engines(tmp_path, cache):
    """``--engine jax`` on the hex6 space: each row's reward is the CPU engine's reward of the
    row's own gait within 0.03 cm (the bound tests/test_other_spaces.py measures for 2-regulator
    robots: 0.007 cm)."""
    pytest.importorskip("jax")
    hex6 = resolve_space("hex6")
    designs = parse_designs("2", hex6)[:2]
    out = tmp_path / "gt"
    spec = ";".join(",".join(map(str, d)) for d in designs)
    assert cli_main(["groundtruth", "--out", str(out), "--space", "hex6", "--duration", "1.0", "--designs", spec,
                     "--engine", "jax", "--jax-batch", "4", *TINY]) == 0
    cfg, res, _ = load_groundtruth(out)
    assert set(res) == set(designs)
    for design, row in res.items():
        cpu, diverged = DesignEvaluator(design, cfg)(PeriodicGait.from_dict(row.gait), cfg.duration)
        assert not diverged and abs(cpu - row.reward_cm) <= 0.03, (design, cpu, row.reward_cm)


@pytest.mark.parametrize("name", ["random", "tpe"])
def test_algorithms_propose_designs_and_gaits_of_the_configs_space(name):
    """The baseline algorithms search hex6's canonical designs with gaits of its 2 regulators
    (no simulation: each proposal is checked, then given a made-up return)."""
    from softcrawl.codesign.algorithms import make_algorithm

    hex6 = resolve_space("hex6")
    designs = parse_designs("2", hex6)
    algo = make_algorithm(name, designs, GroundTruthConfig(space="hex6"), seed=0, evals_per_design=3, cycles=(2,))
    for _ in range(8):
        (p,) = algo.propose()
        assert p.design in designs and p.design == hex6.canonicalize(p.design)
        k = np.array([p.gait.pressure_at(t) for t in (0.0, 1.0)])
        assert k.shape == (2, 2) and np.all((0 <= k) & (k <= 90))
        used = max(p.design)  # regulators the design uses; the others stay vented
        assert np.all(k[:, used:] == 0)
        algo.tell([p], [float(sum(p.design))])
    assert algo.incumbent in designs
