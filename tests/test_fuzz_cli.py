"""Fuzz tests (hypothesis) of the CLI's user inputs: designs, action CSVs, ``--set`` strings and
run folders with missing, corrupt or crafted files."""

from __future__ import annotations

import pickle
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softcrawl.cli import main
from softcrawl.codesign.config import override, preset
from helpers import Evil, file_tree


class _Reached(BaseException):
    """The input was accepted and the expensive work was about to start (stopped here)."""


def _stop(*a, **k):
    raise _Reached


def _check_cli(capsys, argv, root: Path, out: Path | None) -> int | None:
    """Run ``main(argv)``; a refusal must be exit code 2 with one line and no traceback, and
    nothing outside ``out`` may be created or deleted. Returns the exit code (None: accepted)."""
    keep = (lambda rel: out is None or not (root / rel).resolve().is_relative_to(out.resolve()))
    before = {k: v for k, v in file_tree(root).items() if keep(k)}
    try:
        rc = main([str(a) for a in argv])
    except _Reached:
        rc = None
    except SystemExit as exc:  # argparse: a malformed command line
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    if rc not in (None, 0):
        assert rc == 2 and err and "\n" not in err, (rc, err)
    after = {k: v for k, v in file_tree(root).items() if keep(k)}
    assert set(after) == set(before), set(after) ^ set(before)
    return rc


_DESIGN = st.one_of(st.text(alphabet="0123,- x9.", max_size=24),
                    st.lists(st.integers(-2, 5), max_size=10).map(lambda v: ",".join(map(str, v))))
_CSV = st.text(alphabet="0123456789.,-+e \n#abp", max_size=80)
_KEYS = ["n_envs", "total_steps", "seed", "backend", "sac.batch_size", "sac.net_arch", "sac.gamma", "env.legs",
         "env.model", "env.dt", "env.observe_state", "env.reduction", "design.untried", "nope", "sac", "env.nope"]
_VALUES = st.one_of(st.sampled_from(["0", "-1", "1e9", "[0]", "[]", "[3,7]", "true", "null", '"x"', "1.5", "{}",
                                     "[64, true]", "nan", '"ray"', "", "=", "[[1]]"]),
                    st.text(alphabet='0123456789[]{}",.-aetrun', max_size=12))


@settings(max_examples=60, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(design=_DESIGN, csv_text=st.one_of(st.none(), _CSV),
       duration=st.sampled_from(["0.01", "-1", "nan", "1e12", "x"]))
def test_fuzz_simulate_inputs(design, csv_text, duration, monkeypatch_module, capsys):
    import softcrawl.cli.simulate as sim
    from softcrawl.design.space import validate_design
    from softcrawl.gaits import read_actions_csv

    monkeypatch_module.setattr(sim, "build_robot", _stop)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        argv = ["simulate", f"--design={design}", f"--duration={duration}", "--out", root / "out", "--no-progress"]
        if csv_text is not None:
            (root / "a.csv").write_text(csv_text)
            argv += ["--actions", root / "a.csv"]
        rc = _check_cli(capsys, argv, root, root / "out")
        if rc is None:  # accepted: then every input was valid
            validate_design(design)
            if csv_text is not None:
                read_actions_csv(root / "a.csv")
        assert not (root / "out").exists()


@settings(max_examples=60, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(sets=st.lists(st.tuples(st.sampled_from(_KEYS), _VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"), min_size=1,
                     max_size=3))
def test_fuzz_train_set_strings(sets, monkeypatch_module, capsys):
    import softcrawl.cli.train as train_cli

    monkeypatch_module.setattr(train_cli, "train_and_report", _stop)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        argv = ["train", "--preset", "smoke", "--out", root / "run"]
        for s_ in sets:
            argv += ["--set", s_]
        rc = _check_cli(capsys, argv, root, root / "run")
        if rc is None:
            override(preset("smoke"), sets)  # accepted only if valid
        assert not (root / "run").exists()


_RUN_FILES = ["config.json", "episodes.csv", "sessions.csv", "distribution.csv", "checkpoints/latest",
              "checkpoints/LATEST/state.json", "checkpoints/LATEST/manifest.json", "checkpoints/LATEST/learner.msgpack",
              "checkpoints/LATEST/replay_buffer.npz", "checkpoints/LATEST", "checkpoints", "snapshots/t-0000000040.npz",
              "snapshots", "logs", "report"]
_DAMAGE = ["delete", "empty", "garbage", "crafted", "flip", "link-out", "json-list"]


@settings(max_examples=25, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(damage=st.lists(st.tuples(st.sampled_from(_RUN_FILES), st.sampled_from(_DAMAGE)), min_size=1, max_size=3),
       command=st.sampled_from(["report", "evaluate", "resume"]), noise=st.binary(min_size=1, max_size=64))
def test_fuzz_run_folders(trained, damage, command, noise, monkeypatch_module, capsys):
    import softcrawl.cli.train as train_cli
    import softcrawl.codesign.factory as factory

    monkeypatch_module.setattr(factory, "env_fn", _stop)  # evaluate: stop once the policy is loaded
    monkeypatch_module.setattr(train_cli, "train_and_report", _stop)  # resume: stop before training
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        run = root / "run"
        shutil.copytree(trained, run, symlinks=True)
        marker, outside = root / "pwned", root / "outside"
        outside.mkdir()
        (outside / "keep.txt").write_text("not yours")
        for rel, how in damage:
            p = run / rel.replace("LATEST", "step-0000000160")
            if any(q.is_symlink() for q in p.parents if q.is_relative_to(run)) or not p.parent.is_dir():
                continue  # an earlier damage removed or linked away its folder
            if how == "link-out":
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
                p.symlink_to(outside)
            elif p.is_symlink():
                continue  # damaged through the link would be the test's own write outside the run
            elif p.is_dir():
                if how == "delete":
                    shutil.rmtree(p)
            elif how == "delete":
                p.unlink(missing_ok=True)
            elif how == "empty":
                p.write_bytes(b"")
            elif how == "garbage":
                p.write_bytes(noise)
            elif how == "json-list":
                p.write_text("[1, 2]")
            elif how == "crafted":
                p.write_bytes(pickle.dumps({"policy": Evil(marker)}))
            elif how == "flip" and p.is_file() and p.stat().st_size:
                data = bytearray(p.read_bytes())
                data[noise[0] % len(data)] ^= 0xFF
                p.write_bytes(bytes(data))
        argv = {"report": ["report", run, "--no-simulate"],
                "evaluate": ["evaluate", run, "--design", "1,0,0,2,2,0,0,0", "--out", root / "ev", "--no-progress"],
                "resume": ["train", "--resume", "--out", run, "--no-progress"]}[command]
        out = run / "report" if command == "report" else root / "ev" if command == "evaluate" else None

        def outside_report(tree: dict) -> dict:  # report writes report/ (staged in .report.partial-*) only
            return {k: v for k, v in tree.items() if command != "report" or not k.startswith(("report", ".report."))}

        before_run = outside_report(file_tree(run))
        try:
            rc = main([str(a) for a in argv])
        except _Reached:
            rc = None
        err = capsys.readouterr().err.strip()
        assert "Traceback" not in err, err
        if rc not in (None, 0):  # notes ("softcrawl: ...", e.g. a checkpoint fallback) may precede the error
            errors = [line for line in err.splitlines() if not line.startswith("softcrawl: ")]
            assert rc == 2 and len(errors) == 1 and ": error: " in errors[0], (rc, err)
        assert not marker.exists(), "a run file ran code"
        assert [p.name for p in outside.iterdir()] == ["keep.txt"]
        assert outside_report(file_tree(run)) == before_run
        if out is not None and command == "evaluate":
            assert not out.exists()


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()
