"""The commands beyond ``train`` on another design space and task: ``simulate`` and
``sweep-phase --space``/``--task``, ``deploy``'s action file of the rig's width, the randomized
evaluation's outputs in the task's unit and the space's regulators, the turning baseline of a
space, the report's baseline section on another space, and ``check_reduction``'s part check."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers import one_line_error

from softcrawl.cli import main
from softcrawl.design.resolve import resolve_space
from softcrawl.design.space import BASELINE_DESIGN, DEFAULT_SPACE
from softcrawl.design.spacefile import shipped_space_path

HEX6 = resolve_space("hex6")
#: A coarse, short episode of the reduced hex6 model (25 mm disk, 0.02 s steps).
QUICK = ["--disk-mesh-size", "25", "--dt", "0.02", "--no-progress", "--no-animation"]


def _csv(path, rows):
    path.write_text("\n".join(",".join(map(str, r)) for r in rows) + "\n")
    return path


# -- simulate / sweep-phase: refusals before any model is built ----------------------------------
@pytest.mark.parametrize("argv, needle", [
    (["--design", "1,0,2,1,0,2", "--actions", "A3"], "expected 2 columns, got 3"),
    (["--design", "1,0,0,2,2,0,0,1"], "hex6"),  # a paper design: 8 values for 6 slots
    (["--design", "1,0,3,1,0,2"], "hex6"),  # regulator 3 of 2
    ([], "give --design: 6 comma-separated slot values in 0..2 for the design space 'hex6'"),
    (["--design", "1,0,2,1,0,2", "--gait", "paper-best"], "--gait paper-best drives the paper's 3 regulators"),
])
def test_simulate_on_another_space_refuses_bad_input_in_one_line(capsys, tmp_path, argv, needle):
    a3 = _csv(tmp_path / "a3.csv", [("p1", "p2", "p3"), (10, 20, 30)])
    out = tmp_path / "out"
    argv = [str(a3) if a == "A3" else a for a in argv]
    one_line_error(capsys, main(["simulate", "--space", "hex6", *argv, "--out", str(out), *QUICK]), needle)
    assert not out.exists()


def test_sweep_phase_and_simulate_refuse_an_unknown_space_and_task(capsys, tmp_path):
    out = tmp_path / "out"
    one_line_error(capsys, main(["sweep-phase", "--space", "nosuch", "--out", str(out)]), "no shipped design space")
    one_line_error(capsys, main(["sweep-phase", "--space", "hex6", "--out", str(out)]), "give --design")
    one_line_error(capsys, main(["simulate", "--task", "spin", "--out", str(out)]), "--task: unknown task 'spin'")
    one_line_error(capsys, main(["simulate", "--task", '{"name": "turning", "speed": 1}', "--out", str(out)]),
                   "--task: task 'turning' has no setting 'speed'")
    assert not out.exists()


def test_simulate_hex6_with_a_task_reports_its_return_in_its_unit(capsys, tmp_path):
    """A 0.2 s hex6 episode driven by a 2-column action file: ``heading`` at 0 deg (a JSON table;
    the +x displacement, i.e. forward) returns summary.json's reward in cm to 1e-9; ``turning``'s
    return is in deg."""
    actions = _csv(tmp_path / "a2.csv", [("p1", "p2"), (60, 20)])
    out = tmp_path / "heading"
    assert main(["simulate", "--space", "hex6", "--design", "1,0,2,1,0,2", "--actions", str(actions),
                 "--task", '{"name": "heading", "heading_deg": 0}', "--duration", "0.2", "--frames-every", "1",
                 "--out", str(out), *QUICK]) == 0
    said = capsys.readouterr().out
    task = json.loads((out / "task.json").read_text())
    summary = json.loads((out / "summary.json").read_text())
    assert task["task"] == {"name": "heading", "friction": None, "heading_deg": 0.0} and task["unit"] == "cm"
    assert summary["design"] == [1, 0, 2, 1, 0, 2]
    assert task["return_cm"] == pytest.approx(summary["reward_cm"], abs=1e-9)
    assert "task heading: return" in said and " cm (from frames every 1 steps)" in said
    out = tmp_path / "turning"
    assert main(["simulate", "--space", "hex6", "--design", "1,0,2,1,0,2", "--actions", str(actions),
                 "--task", "turning", "--duration", "0.2", "--out", str(out), *QUICK]) == 0
    task = json.loads((out / "task.json").read_text())
    assert task["unit"] == "deg" and math.isfinite(task["return_deg"]) and abs(task["return_deg"]) < 90.0
    assert " deg (from frames every 10 steps)" in capsys.readouterr().out


# -- deploy --------------------------------------------------------------------------------------
def test_deploy_reads_the_actions_csv_with_the_rigs_regulators(capsys, tmp_path):
    a2 = _csv(tmp_path / "a2.csv", [("p1", "p2"), (10, 20)])
    out = tmp_path / "deploy"
    one_line_error(capsys, main(["deploy", "--rig", "sim", "--actions", str(a2), "--out", str(out),
                                 "--no-progress"]), "a2.csv, line 1: expected 3 columns, got 2")
    assert not out.exists()


# -- randomized evaluation and the domain log in the task's unit ----------------------------------
def _randomized(unit, n_regulators, task):
    from softcrawl.codesign.randomization import RandomizedEvaluation
    from softcrawl.robot.domain import DomainRanges

    ranges = DomainRanges(friction=(0.8, 1.6), pressure_gain=(0.9, 1.1))
    rng = np.random.default_rng(0)
    domains = tuple(ranges.draw(rng, n_regulators).as_dict() for _ in range(3))
    return RandomizedEvaluation("run", "ck", (1, 0, 2, 1, 0, 2), ranges, 0, 2.0, False, (1.0, 2.0, 6.0),
                                (False, False, False), domains, task, unit, n_regulators)


def test_randomized_outputs_name_the_tasks_unit_and_the_spaces_regulators(tmp_path):
    """A turning evaluation on 2 regulators: deg keys and columns, gains of regulators 1..2;
    the statistics of returns (1, 2, 6): mean 3, population std sqrt(14/3), median 2."""
    from softcrawl.codesign.randomization import write_randomized

    res = _randomized("deg", 2, {"name": "turning", "friction": None})
    st = res.stats()
    assert st["mean_deg"] == pytest.approx(3.0, abs=1e-12) and st["std_deg"] == pytest.approx(math.sqrt(14 / 3))
    assert st["median_deg"] == 2.0 and "mean_cm" not in st
    write_randomized(tmp_path / "out", res)
    data = json.loads((tmp_path / "out" / "randomization.json").read_text())
    assert data["unit"] == "deg" and data["task"]["name"] == "turning"
    assert data["returns_deg"] == [1.0, 2.0, 6.0] and data["nominal_return_deg"] == 2.0
    assert not any(k.endswith("_cm") for k in data)
    header = (tmp_path / "out" / "randomization.csv").read_text().splitlines()[0]
    assert header == "episode,return_deg,diverged,friction,pressure_gain_1,pressure_gain_2"


def test_a_forward_evaluations_keys_stay_in_cm(tmp_path):
    from softcrawl.codesign.randomization import write_randomized

    res = _randomized("cm", 3, {"name": "forward", "friction": None})
    write_randomized(tmp_path / "out", res)
    data = json.loads((tmp_path / "out" / "randomization.json").read_text())
    assert list(data)[:5] == ["run", "checkpoint", "design", "ranges", "seed"]  # no task keys: as before
    assert "returns_cm" in data and "mean_cm" in data and "unit" not in data
    assert (tmp_path / "out" / "randomization.csv").read_text().splitlines()[0] == \
        "episode,return_cm,diverged,friction,pressure_gain_1,pressure_gain_2,pressure_gain_3"


def test_the_domain_log_of_a_turning_run_on_two_regulators_reads_back(tmp_path):
    from softcrawl.codesign.randomization import DOMAIN_LOG_COLUMNS, DomainLog, log_columns, read_domain_log
    from softcrawl.robot.domain import DomainRanges

    assert log_columns() == DOMAIN_LOG_COLUMNS
    ranges = DomainRanges(pressure_gain=(0.9, 1.1))
    log = DomainLog(tmp_path / "domain.csv", ranges, unit="deg", n_regulators=2)
    draw = ranges.draw(np.random.default_rng(1), 2).as_dict()
    log.write(10, {"episode": {"r": -12.5}, "design": (1, 2, 0, 1, 2, 0), "diverged": False, "domain": draw})
    log.close()
    data = read_domain_log(tmp_path / "domain.csv")
    assert list(data) == ["t", "design", "return_deg", "diverged", "pressure_gain_1", "pressure_gain_2"]
    assert data["return_deg"][0] == -12.5 and data["pressure_gain_2"][0] == pytest.approx(draw["pressure_gain"][1],
                                                                                          rel=1e-5)
    with pytest.raises(ValueError, match="its columns"):  # the same file read as a forward run's
        DomainLog(tmp_path / "domain.csv", ranges, unit="cm", n_regulators=2)


# -- the turning baseline of a space --------------------------------------------------------------
def test_turning_baseline_design_of_a_space():
    from softcrawl.gaits import PeriodicGait, SineGait
    from softcrawl.tasks.baselines import TURNING_BASELINE_DESIGN, turning_baseline_design, turning_gait

    assert turning_baseline_design(DEFAULT_SPACE) == TURNING_BASELINE_DESIGN
    d = turning_baseline_design(HEX6)
    assert d == (1, 2, 0, 1, 2, 0) and HEX6.validate_design(d) == d
    angles = HEX6.slot_angles_deg  # regulator 1 at 30 and 210 deg, regulator 2 at 90 and 270 deg
    assert (angles[0], angles[3], angles[1], angles[4]) == (30.0, 210.0, 90.0, 270.0)
    assert turning_gait(90.0) == SineGait(phase_deg=90.0)  # the paper's space: unchanged
    g, e = turning_gait(90.0, 2), PeriodicGait.expert_sine(90.0, n_regulators=2)
    for t in (0.0, 0.7, 1.9, 3.3):
        np.testing.assert_array_equal(g.pressure_at(t), e.pressure_at(t))


def test_a_space_without_a_turning_design(tmp_path):
    """Five slots (no opposite pairs) or at most 3 legs: no turning baseline; the sweep refuses."""
    from softcrawl.design.spacefile import load_space
    from softcrawl.tasks.baselines import sweep_turning, turning_baseline_design

    text = shipped_space_path("hex6").read_text().replace('reduction = "softcrawl:pneunet6_6mm.npz"\n', "") \
        .replace('reduction_sha256 = "a2f1a7940bf3ddf7f2f7e0d6835fda6a56240217db3f7bcf4cdb1a27197b03b3"\n', "")
    five = tmp_path / "five.toml"
    five.write_text(text.replace("count = 6", "count = 5").replace("mirror_x = true", "mirror_x = false"))
    three = tmp_path / "three.toml"
    three.write_text(text.replace("max_legs = 4", "max_legs = 3"))
    for path in (five, three):
        space = load_space(path, check_geometry=False)
        assert turning_baseline_design(space) is None
        with pytest.raises(ValueError, match="no turning baseline design"):
            sweep_turning(lambda d: None, [0.0], space=space)


def test_every_space_of_two_regulators_has_a_forward_baseline_design(tmp_path):
    """The paper's four legs in an X found again among a space's slots
    (:func:`softcrawl.design.baseline.sine_baseline_design`); a space of one regulator has none
    and its report says so in one line."""
    from softcrawl.codesign.report import no_sine_baseline
    from softcrawl.design.baseline import sine_baseline_design
    from softcrawl.design.spacefile import load_space

    assert sine_baseline_design(DEFAULT_SPACE) == BASELINE_DESIGN
    assert sine_baseline_design(HEX6) == (1, 0, 2, 2, 0, 1)  # front pair 30/330 deg, rear pair 150/210 deg
    one = tmp_path / "one.toml"
    one.write_text(shipped_space_path("hex6").read_text().replace("regulators = 2", "regulators = 1"))
    space = load_space(one, check_geometry=False)
    assert sine_baseline_design(space) is None
    line = no_sine_baseline(space)
    assert "has 1 regulator" in line and "\n" not in line


# -- check_reduction: the reduction's part against the space's -----------------------------------
def _other_part_space(tmp_path):
    """The paper's space with 2.5 mm PneuNet walls naming the paper's reduction (no checksum)."""
    text = shipped_space_path("paper").read_text()
    text = text.replace("wall_thickness_mm = 3.0", "wall_thickness_mm = 2.5")
    text = "\n".join(line for line in text.splitlines() if not line.startswith("reduction_sha256"))
    path = tmp_path / "thin.toml"
    path.write_text(text + "\n")
    return path


def test_check_reduction_refuses_a_reduction_of_another_part(tmp_path):
    from softcrawl.codesign.config import override, preset
    from softcrawl.codesign.factory import check_reduction
    from softcrawl.reduction.artifact import ReductionMismatchError

    check_reduction(preset("smoke"))  # the paper's space and its reduction: accepted
    cfg = override(preset("smoke"), [f'env.space="{_other_part_space(tmp_path)}"'])
    with pytest.raises(ReductionMismatchError, match="wall_thickness"):
        check_reduction(cfg)


def test_train_refuses_a_reduction_of_another_part_in_one_line_and_writes_nothing(capsys, tmp_path):
    out = tmp_path / "run"
    one_line_error(capsys, main(["train", "--preset", "smoke", "--space", str(_other_part_space(tmp_path)),
                                 "--out", str(out), "--no-progress"]), "wall_thickness")
    assert not out.exists()


# -- a smoke-sized turning run on hex6: logs, report (slow: about 2 min on 2 cores) ----------------
@pytest.fixture(scope="module")
def hex6_turning(tmp_path_factory):
    """``softcrawl train --preset smoke --space hex6 --task turning`` (with its report)."""
    run = tmp_path_factory.mktemp("hex6") / "run"
    assert main(["train", "--preset", "smoke", "--space", "hex6", "--task", "turning", "--out", str(run),
                 "--no-progress"]) == 0
    return run


@pytest.mark.slow
def test_a_hex6_turning_runs_logs_and_report(hex6_turning):
    """The scalars are in deg (no cm key); the report has the designs' pictures, the best
    design's section and the turning baseline on hex6's half-turn-symmetric design."""
    header = (hex6_turning / "logs" / "progress.csv").read_text().splitlines()[0].split(",")
    assert {"codesign/mean_return_deg", "codesign/best_return_deg"} <= set(header)
    assert not any(k.startswith("codesign/") and k.endswith("_cm") for k in header)
    report = hex6_turning / "report"
    summary = (report / "summary.md").read_text()
    numbers = json.loads((report / "summary.json").read_text())
    assert (report / "top-1.png").stat().st_size > 0 and (report / "best_design" / "crawl.gif").is_file()
    assert "## Best design's gait" in summary and "design space `hex6`" in summary
    assert "the `turning` return per " in summary and "crawl throughout" not in summary
    assert len(numbers["best_design"]["gait"]["return_per_part_deg"]) == 4
    assert "Hand-made turning gait on the symmetric `1,2,0,1,2,0`" in summary
    assert numbers["baseline"]["design"] == "1,2,0,1,2,0" and len(numbers["baseline"]["phases"]) == 12
    assert (report / "baseline_turning.csv").read_text().splitlines()[0] == "phase_deg,turned_deg,diverged,wall_seconds"


@pytest.mark.slow
def test_a_forward_report_on_hex6_says_why_it_has_no_baseline(hex6_turning, tmp_path):
    """The same run relabelled ``forward``: the baseline section says the paper's design is not
    in hex6; nothing is swept."""
    import shutil

    from softcrawl.codesign.report import write_report

    run = tmp_path / "run"
    shutil.copytree(hex6_turning, run)
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["env"]["task"] = "forward"
    (run / "config.json").write_text(json.dumps(cfg))
    out = write_report(run, simulate=False)
    summary = (out / "summary.md").read_text()
    assert "## Expert baseline\n\nNone: the expert baseline is the paper's design `1,0,0,2,2,0,0,1`" in summary
    assert "baseline" not in json.loads((out / "summary.json").read_text())
    assert not (out / "baseline_sweep").exists()


def test_sweep_phase_on_hex6_matches_simulate_with_the_same_gait(capsys, tmp_path):
    """One phase of ``sweep-phase --space hex6`` (0.05 s) scores what ``simulate --space hex6
    --gait sine`` gets with the same design, phase and robot, to a relative 1e-9."""
    design, common = "1,0,2,1,0,2", ["--space", "hex6", "--duration", "0.05", "--no-progress"]
    assert main(["sweep-phase", *common, "--design", design, "--phases", "90", "--workers", "1",
                 "--out", str(tmp_path / "sweep")]) == 0
    sweep = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert sweep["settings"]["design"] == [1, 0, 2, 1, 0, 2]
    assert main(["simulate", *common, "--design", design, "--gait", "sine", "--phase", "90", "--no-animation",
                 "--out", str(tmp_path / "sim")]) == 0
    reward = json.loads((tmp_path / "sim" / "summary.json").read_text())["reward_cm"]
    assert reward != 0.0  # about 2e-5 cm: the robot moves, so equality says something
    assert sweep["best"]["phase_deg"] == 90.0 and sweep["best"]["reward_cm"] == pytest.approx(reward, rel=1e-9)
