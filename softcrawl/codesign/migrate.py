"""Versioned migration of saved settings: a training run's and a ground truth's ``config.json``.

A ``config.json`` holds its format in ``config_version``; one without it is read as version 1
only if it holds nothing version 1 did not (:func:`check_version_1`: the keys of the documents
and settings every softcrawl of that format wrote), else it is refused, never guessed (a later
format's settings read as version 1 would be migrated into another run). :func:`migrate`
brings its settings object to :data:`CONFIG_VERSION` one step at a time, a function per step,
so every older folder is read by the current code. The steps work on plain JSON objects (no
validation: the config classes' ``from_dict`` does that) and hold the values that reproduce
what the older code simulated, never the current defaults.

Version 2: the robot's settings are one :class:`softcrawl.robot.RobotConfig` object (``env.robot``
of a training run, ``robot`` of a ground truth) instead of fields copied beside the others.
Version 3: a training run's ``sac.learner`` (runs of the older formats trained the torch learner).
Version 4: a training run's ``env.space`` and a ground truth's ``space`` (the design space, a name
or a file; runs and ground truths of the older formats are the paper's space, ``"paper"``); a
run of this format keeps its space file as ``space.toml`` (:mod:`softcrawl.codesign.run`).
Version 5: the ``turning`` task's ``vent_s`` (a training run's ``env.task``, a ground truth's
``task``): folders of the older formats scored a turn while the last action's pressure held,
``vent_s = 0``.
Version 6: a training run's ``rollout`` (runs of the older formats stepped one action at a time,
``"action"``).
Version 7: a training run's ``shortlist`` (runs of the older formats took the most probable design
as theirs: a shortlist of 1, :mod:`softcrawl.codesign.shortlist`).
Version 8: a training run's ``jax_solver`` and ``jax_iterations`` (the JAX backend's contact solve:
runs of the older formats ran 100 Gauss-Seidel sweeps, ``"pgs"`` and 100) and ``jax_precision``
``"auto"`` (older runs saved theirs).
Version 9: a ground truth's ``seeds`` (the search's starting gaits: folders of the older formats
ran the CMA-ES runs from the ``"structured"`` seeds alone).
"""

from __future__ import annotations

#: Current format of the saved settings.
CONFIG_VERSION = 9
#: The first format whose training runs keep their design space as ``space.toml``.
SPACE_VERSION = 4

#: A version-1 run's robot fields with the values its code used when a field was absent (the
#: three added last were written from the version that introduced them: older runs simulated
#: the reference float64, 250 sweeps and every surface node).
_TRAIN_V1_ROBOT = {"model": "reduced", "reduction": None, "leg_mesh_size": 6.0, "disk_mesh_size": 10.0,
                   "refactor_every": None, "rid_dtype": "float64", "dt": 0.02, "contact_max_iterations": 250,
                   "leg_collision_spacing": 0.0}
#: A version-1 ground truth's robot fields and their values when absent (``dt`` null: the
#: robot's default step, 0.01 s; ``rid_dtype``: folders written before the setting computed in
#: float64).
_GT_V1_ROBOT = {"leg_mesh_size": 6.0, "disk_mesh_size": 10.0, "dt": 0.01, "reduction": None, "rid_dtype": "float64"}


def _robot_v1_to_v2(flat: dict, defaults: dict, fixed: dict) -> dict:
    """``flat`` with the keys of ``defaults`` moved into a ``robot`` object (absent or null
    ``dt``: the default; ``fixed``: values the version-1 code always used); unchanged if it
    already has a ``robot`` (written in the version-2 shape)."""
    if "robot" in flat:
        return flat
    out = {k: v for k, v in flat.items() if k not in defaults}
    robot = {k: flat.get(k, v) for k, v in defaults.items()}
    if robot["dt"] is None:
        robot["dt"] = defaults["dt"]
    out["robot"] = {**fixed, **robot}
    return out


def _train_v1_to_v2(config: dict) -> dict:
    env = config.get("env")
    if not isinstance(env, dict):
        return config
    return {**config, "env": _robot_v1_to_v2(env, _TRAIN_V1_ROBOT, {})}


def _groundtruth_v1_to_v2(config: dict) -> dict:
    return _robot_v1_to_v2(config, _GT_V1_ROBOT, {"model": "reduced"})


def _train_v2_to_v3(config: dict) -> dict:
    sac = config.get("sac")
    if not isinstance(sac, dict):
        return config
    return {**config, "sac": {"learner": "torch", **sac}}


def _unchanged(config: dict) -> dict:
    return config


def _train_v3_to_v4(config: dict) -> dict:
    env = config.get("env")
    if not isinstance(env, dict):
        return config
    return {**config, "env": {**env, "space": "paper"}}


def _groundtruth_v3_to_v4(config: dict) -> dict:
    return {**config, "space": "paper"}


def _turning_unvented(task):
    """A task setting (a name or a table) with ``vent_s = 0`` if it is ``turning`` without one."""
    if task == "turning":
        return {"name": "turning", "vent_s": 0.0}
    if isinstance(task, dict) and task.get("name") == "turning" and "vent_s" not in task:
        return {**task, "vent_s": 0.0}
    return task


def _train_v4_to_v5(config: dict) -> dict:
    env = config.get("env")
    if not isinstance(env, dict) or "task" not in env:
        return config
    return {**config, "env": {**env, "task": _turning_unvented(env["task"])}}


def _groundtruth_v4_to_v5(config: dict) -> dict:
    return {**config, "task": _turning_unvented(config["task"])} if "task" in config else config


def _train_v5_to_v6(config: dict) -> dict:
    return {**config, "rollout": "action"}


def _train_v6_to_v7(config: dict) -> dict:
    return {**config, "shortlist": 1}


def _train_v7_to_v8(config: dict) -> dict:
    return {**config, "jax_solver": "pgs", "jax_iterations": 100}


def _groundtruth_v8_to_v9(config: dict) -> dict:
    return {**config, "seeds": "structured"}


#: The keys version 1 had, per kind: of the document (``config.json``), of its settings
#: (``"config"``) and of their sub-objects (dotted paths), from every softcrawl that wrote it
#: (the union of their fields: later ones added some, e.g. ``env.contact_max_iterations``;
#: earlier ones had ``env.settle_steps`` and ``env.tangent_every``).
_V1_KEYS = {
    "train": {
        "": {"version", "config"},
        "config": {"preset", "n_envs", "total_steps", "seed", "backend", "n_workers", "checkpoint_every",
                   "snapshot_every", "keep_checkpoints", "env", "sac", "design"},
        "config.env": {"model", "reduction", "leg_mesh_size", "disk_mesh_size", "refactor_every", "rid_dtype", "dt",
                       "steps_per_action", "contact_max_iterations", "leg_collision_spacing", "n_actions",
                       "observe_state", "settle_speed", "settle_hold", "settle_max_seconds", "settle_steps",
                       "tangent_every", "legs", "max_cached_robots", "randomize"},
        "config.env.randomize": {"friction", "youngs_scale", "mass_scale", "pressure_gain", "pressure_offset",
                                 "tau_inflate", "tau_vent", "control_period"},
        "config.sac": {"policy_lr", "q_lr", "buffer_size", "batch_size", "gamma", "tau", "learning_starts",
                       "utd_ratio", "net_arch", "target_entropy", "timeout", "overlap", "threads", "device"},
        "config.design": {"t0_fraction", "t1_fraction", "h_end", "untried", "beta_max"},
    },
    "groundtruth": {
        "": {"softcrawl", "config"},
        "config": {"duration", "screen_duration", "hold", "cycles", "evals_per_cycle", "popsize", "sigma0",
                   "finalists", "seed", "leg_mesh_size", "disk_mesh_size", "dt", "reduction", "baseline_phases",
                   "rid_dtype"},
    },
}


def check_version_1(kind: str, doc: dict) -> None:
    """Refuse a ``config.json`` document without ``config_version`` that holds a key version 1
    of ``kind`` never had (:data:`_V1_KEYS`): it was written in a later format (its
    ``config_version`` lost), and reading it as version 1 would migrate it into another run
    (a turning run unvented, a hex6 run in the paper's space).

    Raises:
        ValueError: one line naming the keys.
    """
    extra = []
    for path, allowed in _V1_KEYS[kind].items():
        obj = doc
        for part in path.split(".") if path else ():
            obj = obj.get(part) if isinstance(obj, dict) else None
        if isinstance(obj, dict):
            extra += [f"{path}.{k}".lstrip(".").removeprefix("config.") for k in obj if k not in allowed]
    if extra:
        raise ValueError(f"no config_version, and settings format 1 never had ({', '.join(sorted(extra)[:6])}"
                         f"{', ...' if len(extra) > 6 else ''}): written by a later softcrawl and its config_version "
                         "lost; refusing to guess its format (restore config_version)")


#: ``kind -> [step from version 1 to 2, from 2 to 3, ...]``.
STEPS = {"train": [_train_v1_to_v2, _train_v2_to_v3, _train_v3_to_v4, _train_v4_to_v5, _train_v5_to_v6,
                   _train_v6_to_v7, _train_v7_to_v8, _unchanged],
         "groundtruth": [_groundtruth_v1_to_v2, _unchanged, _groundtruth_v3_to_v4, _groundtruth_v4_to_v5, _unchanged,
                         _unchanged, _unchanged, _groundtruth_v8_to_v9]}


def config_version(doc: dict) -> int:
    """The format of a ``config.json`` document (``config_version``; absent: 1).

    Raises:
        ValueError: not an integer in 1..:data:`CONFIG_VERSION` (a newer softcrawl's folder).
    """
    v = doc.get("config_version", 1)
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= CONFIG_VERSION:
        raise ValueError(f"config_version must be an integer in 1..{CONFIG_VERSION} (this softcrawl's formats), "
                         f"got {v!r}")
    return v


def migrate(kind: str, config, version: int):
    """``config`` (a settings object of format ``version``) in the current format; anything
    but an object is returned as it is (``from_dict`` refuses it).

    Raises:
        ValueError: unknown ``kind``.
    """
    if kind not in STEPS:
        raise ValueError(f"kind must be one of {tuple(STEPS)}, got {kind!r}")
    if not isinstance(config, dict):
        return config
    for step in STEPS[kind][version - 1:]:
        config = step(config)
    return config


def read_settings(kind: str, doc) -> dict:
    """The settings object of a ``config.json`` document (``doc["config"]``) in the current format.

    Raises:
        ValueError: ``doc`` is not an object with a ``config`` object, its ``config_version``
            is not one this softcrawl reads, or it has none and is not version 1
            (:func:`check_version_1`).
    """
    if not isinstance(doc, dict) or not isinstance(doc.get("config"), dict):
        raise ValueError('no "config" object')
    if kind in _V1_KEYS and "config_version" not in doc:
        check_version_1(kind, doc)
    return migrate(kind, doc["config"], config_version(doc))
