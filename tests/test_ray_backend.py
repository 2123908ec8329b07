"""Ray backend of the vector env and Ray tasks of the ground truth. A local 2-CPU Ray
is started once for the module (about 10 s); skipped when Ray is not installed."""

from __future__ import annotations

import os
import signal
import sys
import time
from functools import partial

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from softcrawl.codesign.groundtruth import (  # noqa: E402
    DesignResult,
    GroundTruthConfig,
    PeriodicGait,
    load_results,
    run_groundtruth,
)
from softcrawl.design.space import BASELINE_DESIGN, PAPER_BEST_DESIGN  # noqa: E402
from softcrawl.envs import BuildRobot, CrawlerEnv  # noqa: E402
from softcrawl.envs.backends import SerialBackend, SubprocessBackend, make_backend  # noqa: E402
from softcrawl.envs.backends.ray import RayBackend  # noqa: E402
from softcrawl.envs.vec import DesignVecEnv  # noqa: E402
from softcrawl.parallel import ray_map  # noqa: E402
from softcrawl.robot import RobotConfig  # noqa: E402

COARSE = RobotConfig(model="reduced", disk_mesh_size=25)  # about 0.2 s per robot, 400 steps/s
ENV = partial(CrawlerEnv, robot_factory=BuildRobot(COARSE), steps_per_action=2, n_actions=3,
              designs=[PAPER_BEST_DESIGN, BASELINE_DESIGN])


@pytest.fixture(scope="module", autouse=True)
def local_ray(tmp_path_factory):
    os.environ.setdefault("SOFTCRAWL_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # test helpers travel by value
    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1",
                                       "SOFTCRAWL_CACHE_DIR": os.environ["SOFTCRAWL_CACHE_DIR"]}})
    print(f"ray.init: {time.perf_counter() - t0:.1f} s")
    yield
    ray.shutdown()


ACTIONS = np.random.default_rng(0).uniform(-1, 1, (7, 4, 3)).astype(np.float32)


def rollout(backend, kill_after: int | None = None):
    """Fixed actions through a DesignVecEnv (designs from the envs' seeded RNGs)."""
    venv = DesignVecEnv(backend)
    venv.seed(5)
    out = [venv.reset()]
    for k, a in enumerate(ACTIONS):
        if k == kill_after:
            os.kill(backend.actor_pids()[0], signal.SIGKILL)
        obs, rew, done, infos = venv.step(a)
        out += [obs, rew, done, np.array([i.get("episode", {}).get("r", np.nan) for i in infos])]
    designs = list(venv.designs)
    venv.close()
    return out, designs


@pytest.fixture(scope="module")
def reference():
    return rollout(SerialBackend([ENV] * 4))


@pytest.mark.slow
def test_ray_backend_same_results_as_subprocess(reference):
    sub = rollout(SubprocessBackend([ENV] * 4, n_workers=2))
    rb = rollout(RayBackend([ENV] * 4, n_actors=2))
    for a, b, c in zip(reference[0], sub[0], rb[0]):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
    assert reference[1] == sub[1] == rb[1]


@pytest.mark.slow
def test_killed_actor_is_restarted_and_only_its_episodes_replayed(reference):
    backend = RayBackend([ENV] * 4, n_actors=2, max_restarts=2)
    out, designs = rollout(backend, kill_after=4)  # mid-episode (3 actions per episode)
    for a, b in zip(reference[0], out):
        np.testing.assert_array_equal(a, b)  # the run went on with the same results
    assert designs == reference[1] and backend.restarts == 1


def test_make_backend_and_attrs():
    b = make_backend("ray", [ENV] * 3, n_workers=2)
    try:
        assert b.get_attr("n_actions", [0, 2]) == [3, 3]
        b.set_attr("n_actions", 5, [2])
        assert b.get_attr("n_actions", [2, 1]) == [5, 3]
    finally:
        b.close()
    with pytest.raises(ValueError):
        make_backend("mpi", [ENV])


def _dies_once(marker: str, x: int) -> int:
    if x == 1 and not os.path.exists(marker):
        open(marker, "w").close()
        os._exit(1)  # the worker process dies mid-task
    return 10 * x


def test_ray_map_retries_only_the_task_whose_worker_died(tmp_path):
    marker = str(tmp_path / "died")
    assert sorted(ray_map(_dies_once, [(marker, x) for x in range(4)])) == [0, 10, 20, 30]
    assert os.path.exists(marker)


def _count_task(log: str, design, cfg):
    with open(log, "a") as f:
        f.write("".join(map(str, design)) + "\n")
    return DesignResult(tuple(design), float(sum(design)), PeriodicGait.paper_cycle().to_dict(), 3, "step",
                        1, 1, 1.0, 0.0).to_dict()


def test_groundtruth_as_ray_tasks_resumes(tmp_path):
    log = str(tmp_path / "calls.txt")
    designs = [PAPER_BEST_DESIGN, (1, 1, 1, 0, 0, 0, 0, 0), (1, 2, 3, 0, 0, 0, 0, 0)]
    cfg = GroundTruthConfig(baseline_phases=())
    run_groundtruth(designs[:2], tmp_path / "gt", cfg, executor="ray", task=partial(_count_task, log),
                    progress=False, refs=False)
    s = run_groundtruth(designs, tmp_path / "gt", cfg, executor="ray", task=partial(_count_task, log),
                        progress=False, refs=False)
    assert s["designs"] == 3 and len(load_results(tmp_path / "gt")) == 3
    assert sorted(open(log).read().split()) == sorted("".join(map(str, d)) for d in designs)  # each once


@pytest.mark.slow
def test_real_groundtruth_on_ray(tmp_path):
    cfg = GroundTruthConfig(cycles=(2,), evals_per_cycle=3, finalists=1, duration=1.0, screen_duration=0.5,
                            disk_mesh_size=25, baseline_phases=(90,))
    s = run_groundtruth([PAPER_BEST_DESIGN, (1, 1, 1, 0, 0, 0, 0, 0)], tmp_path, cfg, executor="ray", progress=False)
    res = load_results(tmp_path)  # the rank from the two rewards, computed here
    other = res[(1, 1, 1, 0, 0, 0, 0, 0)].reward_cm
    assert s["designs"] == 2 and s["paper_l1"]["rank"] == (1 if res[PAPER_BEST_DESIGN].reward_cm >= other else 2)
    assert s["paper_l1"]["reward_cm"] == res[PAPER_BEST_DESIGN].reward_cm


def test_train_smoke_run_on_ray(tmp_path, capsys):
    """``softcrawl train --preset smoke --set backend="ray"``: the whole run (training on 2 Ray
    actors, checkpoints, report) on the local Ray of this module; a Ray address with another
    backend is refused."""
    import json

    from softcrawl.cli import main

    out = tmp_path / "run"
    rc = main(["train", "--preset", "smoke", "--set", 'backend="ray"', "--workers", "2", "--out", str(out),
               "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    cfg = json.loads((out / "config.json").read_text())["config"]
    assert cfg["backend"] == "ray" and (out / "report" / "summary.md").exists()
    assert (out / "checkpoints" / "latest").read_text().strip() == "step-0000000160"
    rc = main(["train", "--preset", "smoke", "--ray-address", "127.0.0.1:6379", "--out", str(tmp_path / "x")])
    assert rc == 2 and "only by backend" in capsys.readouterr().err


@pytest.mark.slow
def test_whole_episodes_on_ray_equal_stepping_and_survive_a_killed_actor(reference):
    """:meth:`RayBackend.run_episodes` (one call per actor and episode) gives the serial
    backend's per-action transitions; an actor killed before the call is restarted, its envs
    reset to their designs, and the call re-issued with the same results."""
    backend = RayBackend([ENV] * 4, n_actors=2, max_restarts=2)
    serial = SerialBackend([ENV] * 4)
    try:
        designs = [PAPER_BEST_DESIGN, BASELINE_DESIGN] * 2
        for b in (backend, serial):
            b.reset(range(4), designs, [0, 1, 2, 3])
        want = [serial.step(ACTIONS[k]) for k in range(3)]
        os.kill(backend.actor_pids()[0], signal.SIGKILL)
        got = backend.run_episodes(ACTIONS[:3].swapaxes(0, 1))
        assert backend.restarts == 1 and [len(e) for e in got] == [3] * 4
        for i in range(4):
            for k in range(3):
                np.testing.assert_array_equal(got[i][k][0], want[k][i][0])
                assert got[i][k][1:4] == want[k][i][1:4]
    finally:
        backend.close()
        serial.close()
