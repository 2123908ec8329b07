"""The GPU a step is compiled for (:mod:`softcrawl.jaxsim.gpu`): its compute capability, from JAX's
device or a deviceless target configuration, and which GPUs run the engine's Pallas kernels."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest

jax = pytest.importorskip("jax")

H100 = Path(__file__).parents[1] / "benchmarks" / "gpu_targets" / "h100.pbtxt"


def test_a_target_configurations_compute_capability_is_read():
    """The shipped H100 configuration is 9.0 (its minor absent); a T4's 7.5; a configuration
    without one is refused."""
    from softcrawl.jaxsim.gpu import target_capability

    assert target_capability(H100.read_text()) == (9, 0)
    t4 = 'gpu_device_info {\n  core_count: 40\n  cuda_compute_capability {\n    major: 7\n    minor: 5\n  }\n}\n'
    assert target_capability(t4) == (7, 5)
    with pytest.raises(ValueError, match="cuda_compute_capability"):
        target_capability('gpu_device_info {\n  core_count: 40\n}\nplatform_name: "CUDA"\n')


def test_gpus_older_than_ampere_run_xlas_forms(monkeypatch):
    """XLA compiles Pallas' Triton kernels for compute capability 8.0 and up only: a T4 (7.5) and a
    V100 (7.0) get no CUDA branch (XLA's form serves them, as other platforms), an A100, H100 and
    RTX 4090 get the kernel; without a GPU or a deviceless target the kernel branch stays (it is
    only compiled for a GPU); an older GPU is told why its step is slower. A deviceless target is
    JAX's GPU where there is none."""
    from softcrawl.jaxsim import gpu

    kernel = object()
    for capability, runs in (((7, 5), False), ((7, 0), False), ((8, 0), True), ((8, 9), True), ((9, 0), True),
                             (None, True)):
        monkeypatch.setattr(gpu, "compute_capability", lambda c=capability: c)
        monkeypatch.setattr(gpu, "_warned", False)
        assert gpu.runs_kernels() == runs
        if runs:
            assert gpu.cuda_kernel(kernel) == {"cuda": kernel}
        else:
            with pytest.warns(UserWarning, match=r"compute capability {}\.{}".format(*capability)):
                assert gpu.cuda_kernel(kernel) == {}
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # once a process
                assert gpu.cuda_kernel(kernel) == {}
    monkeypatch.undo()
    if all(d.platform == "cpu" for d in jax.devices()):  # no GPU here: the recorded target, else none
        try:
            gpu.set_target((7, 5))
            assert gpu.compute_capability() == (7, 5) and not gpu.runs_kernels()
        finally:
            gpu.set_target(None)
        assert gpu.compute_capability() is None


@pytest.mark.parametrize("config", sorted((H100.parent).glob("*.pbtxt")), ids=lambda p: p.stem)
def test_every_shipped_target_configuration_names_its_compute_capability(config):
    """``benchmarks/gpu_targets/``: each configuration has a CUDA compute capability, 7.5 to 12.0."""
    from softcrawl.jaxsim.gpu import target_capability

    assert (7, 5) <= target_capability(config.read_text()) <= (12, 0)


def _timed(batch, ms, settings, **agreement):
    """A line of ``step_cost.py --time --reference`` for one batch of one form."""
    base = {"precision": "float32", "solver": "apgd", "iterations": 48, "delassus": "fused16", "rid_form": None,
            "cholesky": "kernel", "pairs_dot": None, "resident_rows": None, "operator_parts": True,
            "unroll_pivots": 0, "selection": "xla"}
    return {"batch": batch, "ms_per_step": ms, "bad_robots": 0, **base, **settings, **agreement,
            "form_keys": list(base)}


def test_the_gpu_verdict_makes_a_form_the_default_by_the_stages_rule(tmp_path, capsys):
    """``benchmarks/gpu_verdict.py``: against the first form (the baseline, which stored the
    reference), a form faster at both sizes whose robots end within 0.5 mm (99th percentile) with
    no extra invalid robot becomes the default; one slower at one size, one 0.6 mm off, one with a
    robot invalid that the baseline keeps, do not; one timed at 96 robots only (its call ran out)
    is undecided; lines of a form not compared with the baseline are refused."""
    from helpers import benchmark_module

    verdict = benchmark_module("gpu_verdict")
    ok = {"reference_p99_robot_distance_mm": 0.04, "bad_robots_here_only": 0}
    lines = [_timed(96, 1.20, {}, reference="stored"), _timed(16384, 120.0, {}, reference="stored"),
             _timed(96, 1.00, {"selection": "kernel"}, **ok), _timed(16384, 100.0, {"selection": "kernel"}, **ok),
             _timed(96, 1.00, {"resident_rows": 128}, **ok), _timed(16384, 121.0, {"resident_rows": 128}, **ok),
             _timed(96, 1.00, {"unroll_pivots": 36}, **{**ok, "reference_p99_robot_distance_mm": 0.6}),
             _timed(16384, 90.0, {"unroll_pivots": 36}, **ok),
             _timed(96, 1.00, {"rid_form": "kernel"}, **ok),
             _timed(16384, 90.0, {"rid_form": "kernel"}, **{**ok, "bad_robots_here_only": 1}),
             _timed(96, 0.90, {"rid_form": "kernel", "selection": "kernel"}, **ok)]
    judged = verdict.verdicts(lines)
    assert [v["form"] for v in judged] == [{"selection": "kernel"}, {"resident_rows": 128}, {"unroll_pivots": 36},
                                           {"rid_form": "kernel"}, {"rid_form": "kernel", "selection": "kernel"}]
    assert [v["default"] for v in judged] == [True, False, False, False, False]
    assert [v["decided"] for v in judged] == [True, True, True, True, False]
    assert judged[0]["speedup"] == {"96": 1.2, "16384": 1.2} and judged[2]["p99_mm"] == 0.6
    path = tmp_path / "candidates.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    verdict.main([str(path)])
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert summary == {"make_default": [{"selection": "kernel"}],
                       "undecided": [{"rid_form": "kernel", "selection": "kernel"}]}
    with pytest.raises(ValueError, match="not compared"):
        verdict.verdicts(lines[:2] + [_timed(96, 1.0, {"selection": "kernel"})])
    with pytest.raises(ValueError, match="without form_keys"):
        verdict.verdicts([{k: v for k, v in line.items() if k != "form_keys"} for line in lines])
    with pytest.raises(ValueError, match="no timed lines"):
        verdict.verdicts([{"batch": 96, "dependent_ops_per_step": 127.44}])
