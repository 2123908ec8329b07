"""A run folder's files are read through ``softcrawl.safeio``: a corrupt ``config.json``,
``manifest.json``, ``state.json`` or ``latest`` is one clear error line or the documented
fallback, never a traceback; ``state.json`` keeps the NaN softcrawl writes in it."""

from __future__ import annotations

import json
import math

import pytest

from softcrawl.codesign.checkpoints import CHECKPOINT_FORMATS, _sha256, checkpoint_files, sampler_state_to_json
from softcrawl.codesign.config import preset
from softcrawl.codesign.factory import make_sampler
from softcrawl.codesign.run import Run


def _checkpoint(run: Run, step: int, state: bytes):
    """A torch-learner checkpoint folder whose manifest matches its files (placeholder model and buffer)."""
    ck = run.checkpoints_dir / f"step-{step:010d}"
    ck.mkdir(parents=True)
    (ck / "model.pt").write_bytes(b"model")
    (ck / "replay_buffer.npz").write_bytes(b"buffer")
    (ck / "state.json").write_bytes(state)
    files = {f: _sha256(ck / f) for f in checkpoint_files("torch")}
    (ck / "manifest.json").write_text(json.dumps({"format": CHECKPOINT_FORMATS["torch"], "files": files}))
    return ck


def _state() -> dict:
    sampler = make_sampler(preset("smoke"))
    return {"num_timesteps": 10, "n_updates": 1, "episode_num": 2, "next_designs": None,
            "sampler": sampler_state_to_json(sampler.state_dict())}


def test_state_json_keeps_the_nan_of_untried_designs(tmp_path):
    run = Run(tmp_path)
    text = json.dumps(_state())
    assert "NaN" in text  # every untried design's latest return
    ck = _checkpoint(run, 10, text.encode())
    state = run.read_checkpoint_state(ck)
    returns = state["sampler"]["distribution"]["returns"]
    assert len(returns) == 280 and all(math.isnan(v) for v in returns)


@pytest.mark.parametrize("data", [b"{", b"[" * 100_000 + b"]" * 100_000, b'{"sampler": 1}', b"\xff"])
def test_a_corrupt_state_json_is_one_error_line(tmp_path, data):
    run = Run(tmp_path)
    ck = _checkpoint(run, 10, data)
    with pytest.raises(ValueError) as err:
        run.read_checkpoint_state(ck)
    msg = str(err.value)
    assert "state.json" in msg and "\n" not in msg and len(msg) < 500


def test_a_corrupt_manifest_or_latest_falls_back_to_a_complete_checkpoint(tmp_path, capsys):
    run = Run(tmp_path)
    good = _checkpoint(run, 10, json.dumps(_state()).encode())
    bad = _checkpoint(run, 20, json.dumps(_state()).encode())
    (bad / "manifest.json").write_text('{"format": NaN, "files": {}}')
    assert run.check_checkpoint(bad) == "manifest.json is missing or damaged"
    (run.checkpoints_dir / "latest").write_bytes(b"step-\xff")
    assert run.latest_checkpoint() == good
    err = capsys.readouterr().err
    assert "not a checkpoint of this run" in err and err.count("\n") == 1


def test_a_corrupt_config_json_is_one_error_line(tmp_path):
    run = Run(tmp_path)
    for data in (b"{", b'{"config": {"n_envs": NaN}}', b"[" * 100_000, b"\xff"):
        (tmp_path / "config.json").write_bytes(data)
        with pytest.raises(ValueError) as err:
            run.read_config()
        msg = str(err.value)
        assert str(tmp_path / "config.json") in msg and "\n" not in msg
