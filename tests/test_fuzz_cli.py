"""Fuzz tests (hypothesis) of the CLI's user inputs: designs, action CSVs, ``--set`` strings,
run folders with missing, corrupt or crafted files, and design-space files (read in a worker
process under a time and a memory limit)."""

from __future__ import annotations

import contextlib
import io
import multiprocessing
import pickle
import re
import resource
import shutil
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from softcrawl.cli import main
from softcrawl.codesign.config import override, preset
from softcrawl.design.spacefile import load_space, shipped_space_path
from softcrawl.reduction.data import default_reduction_path
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


#: Space-file keys the fuzzer sets (the first or the second line of that key, ``[body]`` then
#: ``[actuator]`` for the keys of both) and values it sets them to (TOML).
_SPACE_KEYS = ["name", "count", "first_angle_deg", "regulators", "min_legs", "max_legs", "mirror_x",
               "bottom_radius_mm", "top_radius_mm", "height_mm", "mesh_size_mm", "mass_kg", "material",
               "n_chambers", "base_length_mm", "tooth_gap_mm", "wall_thickness_mm", "paper_thickness_mm", "reduction",
               "reduction_sha256"]
_SPACE_VALUES = st.one_of(
    st.sampled_from(["0", "-1", "1", "2", "3", "6", "7", "16", "17", "100", "128", "129", "1000000000",
                     "9223372036854775807", "1e-9", "0.05", "1e300", "nan", "inf", "-inf", "0.5", "true", "false",
                     "[]", "{}", '"x"', '""', '"\\u001b]0;owned\\u0007"', '"a\\u202eb"', '"a\\u0000b"', '"../../x"',
                     '"leg.txt"', '"softcrawl:../x.npz"', '"softcrawl:nope.npz"', '"/dev/zero"', '"../up.npz"',
                     f'"{"n" * 65}"', "[0.0, 90.0]", '{ youngs_modulus_kpa = 1e300, poisson_ratio = 0.3 }']),
    st.integers(-3, 300).map(str))
#: Limits of one space file's command: seconds, and address space beyond the worker's own after
#: its imports (bytes).
_SPACE_SECONDS, _SPACE_BYTES = 60, 1 << 30


def _init_space_worker() -> None:
    """Initializer of the :func:`space_worker` process: ``train`` stopped before training, and
    the address space limited to what the imports took plus :data:`_SPACE_BYTES`."""
    import softcrawl.cli.train as train_cli

    train_cli.train_and_report = _stop
    in_use = int(Path("/proc/self/statm").read_text().split()[0]) * resource.getpagesize()
    resource.setrlimit(resource.RLIMIT_AS, (in_use + _SPACE_BYTES, resource.getrlimit(resource.RLIMIT_AS)[1]))


def _space_command(argv: list[str]) -> tuple:
    """``main(argv)`` in the worker: ``(exit code or None if accepted, stdout, stderr)``; an
    exception (a MemoryError past the limit) comes back as a "Traceback" line."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except _Reached:
            rc = None
        except SystemExit as exc:
            rc = exc.code
        except BaseException as exc:  # noqa: BLE001 - reported to the test, which fails on it
            return 99, out.getvalue(), f"Traceback: {type(exc).__name__}: {exc}"[:2000]
    return rc, out.getvalue()[-20_000:], err.getvalue()[-20_000:]


@pytest.fixture(scope="module")
def space_worker():
    """One spawned process (a fresh interpreter: no threads forked) running the space files'
    commands under a memory limit (:func:`_init_space_worker`)."""
    pool = multiprocessing.get_context("spawn").Pool(1, initializer=_init_space_worker)
    yield pool
    pool.terminate()
    pool.join()


@settings(max_examples=40, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(base=st.sampled_from(["paper", "hex6"]), command=st.sampled_from(["designs", "train"]),
       edits=st.lists(st.tuples(st.sampled_from(_SPACE_KEYS), st.integers(0, 1), _SPACE_VALUES), min_size=1,
                      max_size=3))
# the enumeration and memory cases: few designs in many slots (3^100 and 10^32 slot-value
# combinations were enumerated: a hang), a billion slots (their angles were built: a MemoryError)
@example(base="hex6", command="designs", edits=[("count", 0, "100"), ("min_legs", 0, "1"), ("max_legs", 0, "1"),
                                                  ("mirror_x", 0, "false")])
@example(base="hex6", command="train", edits=[("count", 0, "100"), ("min_legs", 0, "1"), ("max_legs", 0, "1"),
                                                ("mirror_x", 0, "false")])
@example(base="paper", command="train", edits=[("count", 0, "32"), ("regulators", 0, "9"), ("min_legs", 0, "1"),
                                                 ("max_legs", 0, "1")])
@example(base="paper", command="designs", edits=[("count", 0, "1000000000")])
@example(base="paper", command="train", edits=[("count", 0, "1000000000")])
def test_fuzz_space_files(base, command, edits, space_worker):
    """A space file with keys set to extreme, malformed or hostile values: ``designs count`` and
    ``train`` (stopped before training) accept it, printing only printable text, or refuse it
    in one line with exit code 2; never a traceback, a hang (60 s) or more than 1 GiB; a
    refused ``train`` leaves no folder."""
    text = shipped_space_path(base).read_text()
    for key, which, value in edits:
        lines = [m for m in re.finditer(rf"^{key} = .*$", text, flags=re.M)]
        if lines:
            m = lines[min(which, len(lines) - 1)]
            text = text[:m.start()] + f"{key} = {value}" + text[m.end():]
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        (root / "sub").mkdir()
        path = root / "sub" / "s.toml"
        path.write_text(text)
        shutil.copy(default_reduction_path(), root / "up.npz")  # a reduction out of the space file's folder
        argv = {"designs": ["designs", "count", "--space", str(path)],
                "train": ["train", "--preset", "smoke", "--space", str(path), "--out", str(root / "run"),
                          "--no-progress"]}[command]
        try:
            rc, out, err = space_worker.apply_async(_space_command, (argv,)).get(timeout=_SPACE_SECONDS)
        except multiprocessing.TimeoutError:
            space_worker.terminate()  # the later examples fail at once instead of waiting
            raise AssertionError(f"no answer in {_SPACE_SECONDS} s (a hang, or the worker killed):\n{text}") from None
        assert "Traceback" not in err, err
        if rc in (None, 0):  # accepted: a valid space, its text printable
            load_space(path)
            assert all(line.isprintable() for line in out.splitlines()), out
        else:
            line = err.strip()
            assert rc == 2 and line and "\n" not in line and line.isprintable(), (rc, err)
            assert not (root / "run").exists()


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()
