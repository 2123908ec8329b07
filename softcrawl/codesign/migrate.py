"""Versioned migration of saved settings: a training run's and a ground truth's ``config.json``.

A ``config.json`` holds its format in ``config_version`` (absent: version 1); :func:`migrate`
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
"""

from __future__ import annotations

#: Current format of the saved settings.
CONFIG_VERSION = 5
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


#: ``kind -> [step from version 1 to 2, from 2 to 3, ...]``.
STEPS = {"train": [_train_v1_to_v2, _train_v2_to_v3, _train_v3_to_v4, _train_v4_to_v5],
         "groundtruth": [_groundtruth_v1_to_v2, _unchanged, _groundtruth_v3_to_v4, _groundtruth_v4_to_v5]}


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
        ValueError: ``doc`` is not an object with a ``config`` object, or its ``config_version``
            is not one this softcrawl reads.
    """
    if not isinstance(doc, dict) or not isinstance(doc.get("config"), dict):
        raise ValueError('no "config" object')
    return migrate(kind, doc["config"], config_version(doc))
