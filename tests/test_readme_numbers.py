"""The README's and docs/results.md's figures that are cheap to check: the training presets'
table and episode, the shipped ground truth of the three-legged designs, the pressure warp, the
design space's size, the settling of a robot to rest and the README's `demo` sentence against the
seeds docs/results.md records. Figures that take minutes to hours (the
20-s crawls, the reduction's validation, the speed-ups, the co-design runs, the expert baseline's
phase sweep) are in docs/results.md, each with the command that reproduces it."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SHIPPED_GT = ROOT / "benchmarks" / "groundtruth" / "three-legged"


def _readme_presets() -> dict[str, list[str]]:
    """The README's preset table: ``{name: [envs, transitions, designs, schedule]}``."""
    rows = re.findall(r"^\| `(\w+)` \| (.+) \|$", README.read_text(), flags=re.M)
    return {name: [c.strip() for c in cells.split("|")] for name, cells in rows}


def _count(text: str) -> int:
    """``"1M"``, ``"64K"``, ``"6,972"`` as an integer."""
    m = re.fullmatch(r"([\d,]+)([KM]?)", text)
    return int(m.group(1).replace(",", "")) * {"": 1, "K": 1_000, "M": 1_000_000}[m.group(2)]


@pytest.mark.skipif(not README.exists(), reason="README.md not in this tree")
def test_preset_table_matches_the_presets():
    """Envs, transitions, designs (6,972 for all leg counts, 280 three-legged), updates per
    transition and batch size of each preset as the README's table states them."""
    from softcrawl.codesign.config import preset

    table = _readme_presets()
    assert set(table) == {"paper", "reference", "crawl", "demo", "smoke"}
    for name, (envs, transitions, designs, schedule) in table.items():
        cfg = preset(name)
        assert cfg.n_envs == int(envs) and cfg.total_steps == _count(transitions), name
        n_designs = 6_972 if designs.startswith("all 6,972") else 280
        assert len(cfg.env.designs()) == n_designs, name
        if "25 mm disk" in designs or designs == "as `crawl`":
            assert cfg.env.robot.disk_mesh_size == 25.0, name
        per = re.search(r"1 update per (\d+ )?transition", schedule)
        if per:
            assert cfg.sac.utd_ratio == pytest.approx(1 / int(per.group(1) or 1)), name
        batch = re.search(r"batch (\d+)", schedule)
        if batch:
            assert cfg.sac.batch_size == int(batch.group(1)), name


def test_training_episode_and_step_of_the_presets():
    """README: every preset but ``smoke`` runs the paper's episode (20 actions of 1 s) at dt
    0.02 s with float32 element products and at most 100 sweeps per contact chunk; ``demo`` is
    400 episodes of the 280 three-legged designs on 8 envs in 2 worker processes."""
    from softcrawl.codesign.config import preset

    for name in ("paper", "reference", "crawl", "demo"):
        e = preset(name).env
        assert e.n_actions == 20 and e.robot.dt * e.steps_per_action == pytest.approx(1.0), name
        assert e.robot.dt == 0.02 and e.robot.rid_dtype == "float32" and e.robot.contact_max_iterations == 100, name
    demo = preset("demo")
    assert demo.total_steps // demo.env.n_actions == 400 and demo.n_envs == 8 and demo.n_workers == 2
    smoke = preset("smoke").env
    assert smoke.n_actions == 20 and smoke.robot.dt * smoke.steps_per_action * smoke.n_actions == pytest.approx(0.4)


def test_design_space_and_pressure_warp():
    """README: 6,972 canonical bodies; slot i at 22.5 + 45 i degrees from +x; the simulator
    applies sim = 4.0785 real - 20.36 kPa (the paper's calibration; clamped at 0)."""
    from softcrawl.design.space import SLOT_ANGLES_DEG, canonical_designs
    from softcrawl.robot.actuation import PressureCalibration

    assert len(canonical_designs()) == 6_972
    assert SLOT_ANGLES_DEG == tuple(22.5 + 45.0 * i for i in range(8))
    cal = PressureCalibration()  # fitted to the paper's table: equal to the printed digits
    assert cal.a == pytest.approx(4.0785, abs=5e-5) and cal.b == pytest.approx(-20.36, abs=5e-3)
    assert cal.to_sim(np.array([0.0]))[0] == 0.0


@pytest.mark.skipif(not (SHIPPED_GT / "results.jsonl").exists(), reason="shipped ground truth not in this tree")
def test_shipped_groundtruth_is_valid_and_matches_the_documented_figures():
    """``benchmarks/groundtruth/three-legged`` loads as a finished ground truth of all 280
    three-legged designs at the README's command settings (the duty search: 672-678 simulated
    s per design), and gives docs/results.md's table: the best design and its reward, the next two, the ``demo`` runs' designs' and the paper's L1's ranks (designs of
    equal reward share one, as ``regret`` ranks) and rewards, the median, and the expert
    baseline's reward and how many designs beat it (figures rounded to 0.01 cm as printed)."""
    from softcrawl.codesign.config import EnvConfig
    from softcrawl.codesign.groundtruth import load_groundtruth
    from softcrawl.safeio import load_json

    cfg, res, refs = load_groundtruth(SHIPPED_GT)
    assert set(res) == set(EnvConfig(legs=(3,)).designs()) and len(res) == 280
    assert (cfg.robot.disk_mesh_size, cfg.robot.dt, tuple(cfg.cycles), cfg.evals_per_cycle) == (25.0, 0.02, (2, 3, 4), 30)
    assert cfg.seeds == "duty"
    assert not any(r.diverged for r in res.values()) and all(np.isfinite(r.reward_cm) for r in res.values())
    assert all(672.0 <= r.sim_seconds <= 678.0 for r in res.values())
    ranked = sorted(res, key=lambda d: -res[d].reward_cm)
    reward = {d: round(res[d].reward_cm, 2) for d in res}
    rank = {d: 1 + sum(r.reward_cm > res[d].reward_cm for r in res.values()) for d in res}
    assert ranked[:3] == [(0, 0, 0, 1, 2, 3, 0, 0), (0, 0, 0, 1, 2, 1, 0, 0), (0, 0, 1, 2, 1, 0, 0, 0)]
    assert [reward[d] for d in ranked[:3]] == [32.68, 32.66, 32.22]
    assert res[ranked[0]].cycle == 2 and res[ranked[0]].waveform == "step"
    for design in [(0, 0, 0, 1, 1, 1, 0, 0), (0, 0, 0, 1, 1, 2, 0, 0)]:  # the demo runs' designs
        assert (rank[design], reward[design]) == (5, 24.90)
    assert (rank[(0, 0, 1, 1, 1, 0, 0, 0)], reward[(0, 0, 1, 1, 1, 0, 0, 0)]) == (9, 23.95)
    l1 = (1, 0, 0, 2, 2, 0, 0, 0)
    assert (rank[l1], reward[l1]) == (17, 16.92)
    assert round(float(np.median([r.reward_cm for r in res.values()])), 2) == 3.87
    baseline = refs["expert_baseline"]
    assert round(baseline["reward_cm"], 2) == 2.15 and baseline["best_phase_deg"] == 20.0
    assert sum(r.reward_cm > baseline["reward_cm"] for r in res.values()) == 188
    assert round(refs["paper_l1_gait"]["reward_cm"], 2) == 11.39
    summary = load_json(SHIPPED_GT / "summary.json")  # the summary agrees with the results
    assert summary["designs"] == 280 and summary["paper_l1"]["rank"] == 17
    assert summary["designs_beating_expert_baseline"] == 188
    assert [b["rank"] for b in summary["best"]] == [1, 2, 3, 4, 5, 5, 5, 8, 9, 9]


SETTLING_DESIGNS = [(0, 0, 0, 0, 0, 1, 2, 3), (0, 0, 0, 1, 2, 1, 0, 0), (1, 2, 3, 0, 0, 0, 0, 0)]


@pytest.mark.parametrize("dt, steps", [(0.01, (41, 54)), (0.02, (22, 29))])
def test_settling_takes_the_documented_steps(dt, steps):
    """docs/results.md (``python benchmarks/settling.py`` over the 280 three-legged designs, 25 mm
    disk, rest rule 0.5 mm/s for 0.05 s): 41-54 steps to rest at dt 0.01 s, 22-29 at 0.02 s, none
    at the 3 s cap. Three of those designs, each within the documented range widened by 2 steps
    (another CPU's round-off may move a design at the range's edge by a step). Measured here:
    43, 41, 42 steps at 0.01 s (rest speeds 0.31-0.33 mm/s, under the documented 0.36) and 23,
    22, 23 at 0.02 s (rest speeds up to 0.40 mm/s: the 0.02-s step is checked against the rule's
    0.5 mm/s only)."""
    from softcrawl.robot import RobotConfig, Settling, build_robot, settle

    lo, hi = steps
    for design in SETTLING_DESIGNS:
        robot = build_robot(design, RobotConfig(model="reduced", disk_mesh_size=25.0, dt=dt))
        s = settle(robot, Settling(rest_speed=0.5, hold_seconds=0.05))
        assert s.at_rest and lo - 2 <= s.steps <= hi + 2, (design, s.steps)
        assert s.rest_speed <= (0.36 if dt == 0.01 else 0.5), (design, s.rest_speed)


def test_paper_best_design_crawls_the_documented_20_s_on_the_reduced_model():
    """README: the paper's best design with its 3-s gait crawls +11.8 cm in 20 s on the reduced
    model (docs/results.md: +11.78 cm on EPYC; +11.779 cm measured here, 22 s of CPU). The exact
    full-order model's +10.7 cm takes 7.7 min of CPU and stays in docs/results.md. Allowed:
    0.5 cm, for other CPUs' round-off over 20 s of stick-slip; still half the gap to the exact
    model's 10.66 cm (+10.655 cm measured here: the full-order model fails this test), so a
    reduced model that drifted towards it or away fails."""
    from softcrawl.gaits import paper_best_gait
    from softcrawl.robot import RobotConfig, build_robot
    from softcrawl.robot.episode import run_episode

    robot = build_robot((1, 0, 0, 2, 2, 0, 0, 0), RobotConfig(model="reduced"))
    res = run_episode(robot, paper_best_gait(n_actions=20), 20.0, record_every=None, progress=False)
    assert not res.diverged and res.reward_cm == pytest.approx(11.8, abs=0.5), res.reward_cm


def test_the_readmes_demo_sentence_is_the_median_and_range_of_the_recorded_seeds():
    """The README states the ``demo`` outcome as the median and range over the seeds recorded in
    docs/results.md (its table of seeds 0-4 with the shortlist), and the ranks there are the
    shipped ground truth's for the recorded winners."""
    results = (ROOT / "docs" / "results.md").read_text()
    table = results.split("**`demo`, seeds 0–4, with the shortlist**", 1)[1].split("\n\n**", 1)[0]
    rows = re.findall(r"^\| (\d) \| `([\d,]+)` \| \+([\d.]+) cm \| ([\d.]+)× \| \**(\d+) \(", table, flags=re.M)
    assert [int(r[0]) for r in rows] == [0, 1, 2, 3, 4]
    ranks, gaits, ratios = [int(r[4]) for r in rows], [float(r[2]) for r in rows], [float(r[3]) for r in rows]
    text = " ".join(README.read_text().split())
    assert (f"ground-truth rank median {int(np.median(ranks))} (range {min(ranks)}–{max(ranks)}) of 280, its gait "
            f"median +{np.median(gaits):.2f} cm (range +{min(gaits):.2f} to +{max(gaits):.2f}), "
            f"{min(ratios):.1f}–{max(ratios):.1f}× the expert baseline") in text
    with open(SHIPPED_GT / "groundtruth.csv", newline="") as f:
        shipped = {r["design"]: int(r["rank"]) for r in csv.DictReader(f)}
    for seed, design, *_, rank in rows:
        assert shipped[design] == int(rank), seed
