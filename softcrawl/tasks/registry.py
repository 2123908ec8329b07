"""The task registry: name -> task class, and tasks read from a name or a table of settings
(a run's ``EnvConfig.task``, a TOML or JSON table; docs/tasks.md)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from softcrawl.tasks.base import Task
from softcrawl.tasks.builtin import Forward, Heading, Incline, Target, Turning

#: Task name -> class. Register a new task here (docs/tasks.md, "Adding a task").
TASKS: dict[str, type[Task]] = {cls.name: cls for cls in (Forward, Heading, Turning, Target, Incline)}
#: The default task: the paper's.
DEFAULT_TASK = "forward"


def make_task(name: str, **settings) -> Task:
    """The task ``name`` (:data:`TASKS`) with ``settings`` (its fields; the rest default).

    Raises:
        ValueError: an unknown name or setting, or a bad value (one line each).
    """
    if not isinstance(name, str) or name not in TASKS:
        raise ValueError(f"unknown task {name!r}; tasks: {', '.join(TASKS)}")
    cls = TASKS[name]
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise ValueError(f"task {name!r} has no setting {', '.join(map(repr, unknown))}; its settings: "
                         f"{', '.join(known)}")
    return cls(**settings)


def parse_task(spec) -> Task:
    """A task from ``spec``: a :class:`Task`, a name (``"turning"``), or a table with a
    ``name`` and settings (``{"name": "heading", "heading_deg": 90}``).

    Raises:
        ValueError: anything else, or what :func:`make_task` refuses (one line).
    """
    if isinstance(spec, Task):
        return spec
    if isinstance(spec, str):
        return make_task(spec)
    if isinstance(spec, Mapping):
        if "name" not in spec:
            raise ValueError(f"a task table needs a name ({', '.join(TASKS)}), got {dict(spec)!r}")
        settings = {str(k): v for k, v in spec.items() if k != "name"}
        return make_task(spec["name"], **settings)
    raise ValueError(f"a task is a name ({', '.join(TASKS)}) or a table with a name and settings, got {spec!r}")


def task_spec(text: str, what: str = "task") -> str | dict:
    """A task written on a command line: a name (``turning``) or a JSON table of its settings
    (``{"name": "heading", "heading_deg": 90}``), returned as the value of ``EnvConfig.task``
    (the name or the table), checked by :func:`parse_task`.

    Raises:
        ValueError: not a task, or malformed JSON (one line, starting with ``what``).
    """
    from softcrawl.safeio import loads_json

    spec = loads_json(text, what) if text.lstrip().startswith("{") else text.strip()
    try:
        parse_task(spec)
    except ValueError as exc:
        raise ValueError(f"{what}: {exc}") from None
    return spec
