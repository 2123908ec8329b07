"""Process-parallel task runs (one BLAS thread per worker), shared by the phase sweep and
the reduction build; task runs on Ray (:func:`ray_map`, the ground truth's ``executor="ray"``)
and the connection to Ray (:func:`ensure_ray`, shared with the Ray env backend); the
peak-memory monitor of such runs."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator

import psutil

#: Environment of worker processes and Ray workers: one BLAS/OpenMP thread each (parallelism
#: comes from processes).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def default_worker_env() -> None:
    """Set :data:`WORKER_ENV` in this process's environment where a variable is unset (the
    processes it starts inherit it)."""
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)


@contextlib.contextmanager
def _one_blas_thread() -> Iterator[None]:
    """Environment of the processes started inside: :data:`WORKER_ENV` (restored after)."""
    old = {v: os.environ.get(v) for v in WORKER_ENV}
    os.environ.update(WORKER_ENV)
    try:
        yield
    finally:
        for v, val in old.items():
            if val is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = val


def watch_parent(parent_pid: int, interval: float = 2.0) -> None:
    """In a worker process: a daemon thread that ends this process (exit status 1) once the
    process ``parent_pid`` is gone, so that a parent killed without its cleanup (SIGKILL,
    SIGTERM) leaves no worker computing."""
    def watch():
        while psutil.pid_exists(parent_pid):
            time.sleep(interval)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="watch-parent").start()


def _init_worker(parent_pid: int) -> None:
    """Worker initializer. Ctrl-C reaches the whole process group, but only the parent acts on
    it (it stops the workers), so workers ignore SIGINT and print no traceback of their own;
    they end when the parent is gone (:func:`watch_parent`). tqdm's bars get a thread lock
    instead of their default multiprocessing lock: that named semaphore is never unlinked in a
    stopped worker (a "leaked semaphore" warning at exit)."""
    from tqdm import tqdm

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    watch_parent(parent_pid)
    tqdm.set_lock(threading.RLock())


def pool_size(workers: int | None, n_tasks: int) -> int:
    """The processes :func:`run_pool` starts for ``n_tasks`` tasks: ``workers`` (None or 0: the
    CPU count), never more than the tasks, at least 1 (1: it runs them in the calling process)."""
    return max(1, min(workers or os.cpu_count() or 1, n_tasks))


def run_pool(fn: Callable, workers: int | None, tasks: list[tuple], finished: Callable) -> None:
    """``finished(fn(*task))`` for each task, as tasks complete, on ``workers`` spawned
    processes (None: the CPU count; never more than there are tasks; 1: in this process, in
    order). On an error or interrupt, results already computed are still passed to
    ``finished``, the workers are stopped and the error is re-raised. The workers ignore
    SIGINT: Ctrl-C is a ``KeyboardInterrupt`` in the caller only; they end themselves if the
    caller is killed (:func:`watch_parent`)."""
    workers = pool_size(workers, len(tasks))
    if workers == 1:
        for task in tasks:
            finished(fn(*task))
        return
    with _one_blas_thread():  # the workers are spawned on submit, inside this block
        pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_init_worker, initargs=(os.getpid(),))
        futures = [pool.submit(fn, *task) for task in tasks]
    seen = set()
    try:
        for f in cf.as_completed(futures):
            seen.add(f)
            finished(f.result())
    except BaseException:
        for f in futures:  # keep what is done
            if f not in seen and f.done() and not f.cancelled() and f.exception() is None:
                finished(f.result())
        for proc in list((pool._processes or {}).values()):  # no public API before Python 3.14
            proc.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


class PeakMemory:
    """Peak resident memory of this process and of this process with all its child processes
    (e.g. :func:`run_pool` workers), sampled by a background thread while the context is open.

    The sum over processes counts pages they share (libraries) once per process, so
    ``total_mb`` is an upper bound of the memory used. Usage::

        with PeakMemory() as mem:
            ...
        mem.total_mb, mem.main_mb

    Args:
        interval: seconds between samples (a shorter peak between samples is missed).
    """

    def __init__(self, interval: float = 0.2):
        self.interval = interval
        self.total_mb = self.main_mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="peak-memory")

    def sample(self) -> None:
        """Take one sample now."""
        me = psutil.Process()
        main = me.memory_info().rss
        total = main
        for child in me.children(recursive=True):
            try:
                total += child.memory_info().rss
            except psutil.Error:  # the child ended meanwhile
                pass
        self.main_mb = max(self.main_mb, main / 2**20)
        self.total_mb = max(self.total_mb, total / 2**20)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.sample()

    def __enter__(self) -> PeakMemory:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()


#: Seconds a Ray cluster at a given address has to answer before :func:`ensure_ray` gives up
#: (the environment variable ``SOFTCRAWL_RAY_TIMEOUT`` overrides it).
CONNECT_TIMEOUT_S = 30.0


def connect_timeout() -> float:
    """:data:`CONNECT_TIMEOUT_S`, or ``SOFTCRAWL_RAY_TIMEOUT`` (seconds, > 0) if set.

    Raises:
        ValueError: ``SOFTCRAWL_RAY_TIMEOUT`` is not a positive number.
    """
    text = os.environ.get("SOFTCRAWL_RAY_TIMEOUT")
    if text is None:
        return CONNECT_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise ValueError(f"SOFTCRAWL_RAY_TIMEOUT must be a positive number of seconds, got {text!r}")
    return value


def check_address(address: str, timeout: float) -> None:
    """Raise ConnectionError unless the head of the Ray cluster at ``address`` (``host:port``
    or ``ray://host:port``) accepts a TCP connection within ``timeout`` s (retried until then:
    a head that is starting up gets the whole time). ``"auto"`` and addresses without a port
    are left to Ray. Ray itself would retry a silent address for minutes.

    Raises:
        ConnectionError: nothing answers in time. ValueError: a port outside 1..65535.
    """
    import socket

    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit() or not host:
        return
    host = host.strip("[]")
    if not 0 < int(port) < 65536:
        raise ValueError(f"Ray address {address}: the port must be 1..65535")
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        try:
            socket.create_connection((host, int(port)), timeout=max(left, 0.1)).close()
            return
        except OSError as exc:
            if left <= 0.5:
                raise ConnectionError(f"no Ray cluster answers at {address} within {timeout:g} s "
                                      f"({exc.strerror or exc}); start one (ray start --head) or check "
                                      "--ray-address") from None
            time.sleep(min(0.5, left))


def ensure_ray(address: str | None = None, num_cpus: int | None = None):
    """Connect to Ray: the running one if this process already did, else a cluster at
    ``address`` (which must answer within :func:`connect_timeout` s, :func:`check_address`),
    else a new local Ray with ``num_cpus`` CPUs (default: all). Workers get
    :data:`WORKER_ENV`. Returns the ``ray`` module.

    Raises:
        ImportError: Ray is not installed. ConnectionError: no cluster answers at ``address``.
    """
    try:
        import ray
    except ImportError:
        raise ImportError("Ray backends and tasks need Ray: pip install 'softcrawl[ray]' (ray>=2)") from None
    if not ray.is_initialized():
        kw = {"runtime_env": {"env_vars": dict(WORKER_ENV)}, "log_to_driver": False}
        if address:
            check_address(address, connect_timeout())
            ray.init(address=address, **kw)
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, **kw)
    return ray


def _apply(fn: Callable, *args):
    """Ray task body: ``fn(*args)`` (``fn`` may be any picklable callable, e.g. a partial)."""
    return fn(*args)


def ray_map(fn: Callable, args: Iterable[tuple], address: str | None = None, num_cpus: int | None = None,
            max_retries: int = 3) -> Iterator:
    """``fn(*a)`` for each ``a`` in ``args`` as Ray tasks (1 CPU each), yielding results as they
    finish (not in order). A task whose worker process died is retried up to ``max_retries``
    times (only that task); an exception raised by ``fn`` is re-raised here.

    Raises:
        ImportError: Ray missing.
    """
    ray = ensure_ray(address, num_cpus)
    task = ray.remote(num_cpus=1, max_retries=max_retries)(_apply)
    fn_ref = ray.put(fn)
    pending = [task.remote(fn_ref, *a) for a in args]
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])
