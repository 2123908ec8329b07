"""Seeded fuzz tests (hypothesis) of ground-truth tables: ``results.jsonl`` files mixing valid
rows, rows with extra keys, rows with fields deleted or replaced by any JSON value, torn
lines, non-finite rewards, designs outside the space, deep nesting and arbitrary text; and
``config.json`` files of any JSON value. Whatever the table, its readers (``regret``,
``groundtruth``'s summary and resume) use exactly the valid rows, name every other line by
file and line, never write NaN, never change a byte that was there, and fail, if at all, with
one line."""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from groundtruth_helpers import DESIGNS, fake_task, row
from softcrawl.cli import main as cli_main
from softcrawl.codesign import groundtruth_regret as rg
from softcrawl.codesign.groundtruth import (
    DesignResult,
    GroundTruthConfig,
    PeriodicGait,
    design_set_spec,
    gt_robot,
    read_config,
    read_results,
    run_groundtruth,
    write_outputs,
)
from softcrawl.codesign.migrate import CONFIG_VERSION
from softcrawl.design.resolve import write_space_copy
from softcrawl.design.space import PAPER_BEST_DESIGN, canonicalize
from softcrawl.safeio import loads_json

POOL = [*DESIGNS, PAPER_BEST_DESIGN]
FIELDS = list(json.loads(row(POOL[0])))


def _json(floats):
    return st.recursive(st.none() | st.booleans() | st.integers() | st.just(10**400) | floats | st.text(max_size=8),
                        lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
                        max_leaves=8)


_JSON = _json(st.floats())  # NaN and infinities too: json writes them, the readers refuse them
_FINITE_JSON = _json(st.floats(allow_nan=False, allow_infinity=False))
_TEXT = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\n\r"), max_size=40)


@st.composite
def _line(draw):
    """``(line, verdict)``: verdict True (a valid row), False (a bad one) or None (depends on the draw)."""
    design = draw(st.sampled_from(POOL))
    reward = draw(st.floats(-100, 100))
    kind = draw(st.sampled_from(["good", "extra", "mutated", "torn", "nonfinite", "design", "deep", "text"]))
    if kind == "good":
        return row(design, reward_cm=reward), True
    if kind == "extra":
        keys = draw(st.dictionaries(_TEXT.filter(lambda k: k not in FIELDS), _FINITE_JSON, min_size=1, max_size=3))
        return row(design, reward_cm=reward, **keys), True
    if kind == "mutated":
        d = json.loads(row(design, reward_cm=reward))
        for key in draw(st.lists(st.sampled_from(FIELDS), min_size=1, max_size=3, unique=True)):
            if draw(st.booleans()):
                del d[key]
            else:
                d[key] = draw(_JSON)
        return json.dumps(d), None
    if kind == "torn":
        text = row(design, reward_cm=reward)
        return text[: draw(st.integers(1, len(text) - 1))], False
    if kind == "nonfinite":
        return row(design, reward_cm=draw(st.sampled_from([float("nan"), float("inf"), -float("inf")]))), False
    if kind == "design":
        bad = draw(st.sampled_from([[9] * 8, [1, 2], [], [1, 0, 0, 1, 0, 0, 0, 0], [2, 0, 0, 1, 1, 0, 0, 0]]))
        return row(design, design=bad), False
    if kind == "deep":
        n = draw(st.integers(65, 3000))
        return "[" * n + "]" * n, False
    return draw(_TEXT), None


def _folder(root: Path, lines: list[str]) -> Path:
    gt = root / "gt"
    gt.mkdir()
    cfg = GroundTruthConfig(baseline_phases=(), robot=gt_robot(dt=0.02))
    sha = write_space_copy(gt, cfg.space)
    (gt / "config.json").write_text(json.dumps({"config": cfg.to_dict(), "config_version": CONFIG_VERSION,
                                                "space_sha256": sha, "designs": design_set_spec(POOL)}))
    (gt / "results.jsonl").write_text("".join(ln + "\n" for ln in lines))
    return gt


def _check_result(r: DesignResult) -> None:
    assert canonicalize(r.design) == r.design
    assert all(v == v and abs(v) != float("inf") for v in (r.reward_cm, r.sim_seconds, r.wall_seconds))
    assert min(r.evaluations, r.full_evaluations, r.diverged) >= 0
    PeriodicGait.from_dict(r.gait)


@settings(max_examples=30, deadline=None, database=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(lines=st.lists(_line(), min_size=1, max_size=12), chosen=st.sampled_from(POOL))
def test_fuzz_groundtruth_tables(lines, chosen, capsys):
    with tempfile.TemporaryDirectory() as tmp, pytest.MonkeyPatch.context() as mp:
        gt = _folder(Path(tmp), [ln for ln, _ in lines])
        res = gt / "results.jsonl"
        before = res.read_bytes()
        good, bad = read_results(gt)
        bad_lines = {int(re.match(rf"{re.escape(str(res))}, line (\d+)", b).group(1)) for b in bad}
        assert len(bad_lines) == len(bad)
        for n, (text, verdict) in enumerate(lines, start=1):
            if verdict is not None and text.strip():
                assert (n in bad_lines) is not verdict, (n, text, bad)
        assert len(bad) + sum(1 for n, (t, _) in enumerate(lines, 1) if t.strip() and n not in bad_lines) \
            == sum(1 for t, _ in lines if t.strip())
        for r in good.values():
            _check_result(r)
        # the summary: valid rows only, strict JSON
        summary = write_outputs(gt)
        assert summary["designs"] == len(good) and summary["bad_rows"] == bad
        loads_json((gt / "summary.json").read_text())
        # regret: the chosen design's place, or one line saying it is not there
        mp.setattr(rg, "run_choice", lambda run: {"design": chosen, "prob": 0.5, "latest_cm": 0.0, "episodes": 1})
        mp.setattr(rg, "run_settings", lambda run: rg.gt_settings(GroundTruthConfig()))
        capsys.readouterr()
        out_json = Path(tmp) / "regret.json"
        rc = cli_main(["regret", "RUN", "--groundtruth", str(gt), "--no-policy", "--json", str(out_json)])
        err = capsys.readouterr().err
        assert "Traceback" not in err and rc == (0 if chosen in good else 2), err
        if rc == 0:
            r = loads_json(out_json.read_text())
            assert r["placement"]["of"] == len(good)
            assert r["placement"]["reward_cm"] == good[chosen].reward_cm
        else:
            assert err.count("error:") == 1
            assert "not in the ground truth" in err if good else "no finished design" in err
        assert res.read_bytes() == before
        # a resume computes exactly the designs without a valid row and keeps every byte
        calls = []
        run_groundtruth(POOL, gt, None, executor="serial", progress=False, refs=False,
                        task=lambda d, c: calls.append(d) or fake_task(d, c))
        assert sorted(calls) == sorted(d for d in POOL if d not in good)
        assert res.read_bytes().startswith(before) and set(read_results(gt)[0]) == set(POOL)


@settings(max_examples=60, deadline=None, database=None, derandomize=True)
@given(doc=st.one_of(_JSON, st.dictionaries(st.just("config"), _JSON, min_size=1),
                     st.builds(lambda k, v: {"config": {**GroundTruthConfig().to_dict(), k: v}},
                               st.sampled_from(list(GroundTruthConfig().to_dict())), _JSON)))
def test_fuzz_groundtruth_config(doc):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.json"
        path.write_text(json.dumps(doc))
        try:
            cfg = read_config(tmp)
        except ValueError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc)
            return
        assert GroundTruthConfig.from_dict(cfg.to_dict()).to_dict() == cfg.to_dict()
