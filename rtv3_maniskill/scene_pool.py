"""One scene pool for every long run (``rtv3 generate``, ``rtv3 dagger``, ``rtv3 benchmark-shared``).

A run is a list of independent scene jobs. Each worker builds its expensive state once
(``init(setting)``: the env, the planner, the policy) and then runs jobs (``job(state, item)``),
returning plain picklable results; the calling process alone writes the run's record store, so a
run stays resumable and gives the same records whichever executor ran it:

* ``workers=1``, ``executor="local"``: in this process;
* ``workers>1``, ``executor="local"``: that many spawned processes on this machine;
* ``executor="ray"``: ``workers`` Ray actors, each job one task, on a local Ray instance
  (``ray.init(num_cpus=workers)``) or on the cluster at ``ray_address`` (``pip install -e ".[ray]"``).

A worker that fails, while starting or on a job, stops the whole run once, with that worker's
error (:class:`SceneWorkerError`); jobs still queued are cancelled.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator
from typing import Any

EXECUTORS = ("local", "ray")


class SceneWorkerError(RuntimeError):
    """A scene worker failed; the message is the worker's own error (type and text)."""


def _describe(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"


# ----------------------------------------------------------------------------- one worker, any executor


def _start(init: Callable[[Any], Any], setting: Any) -> tuple[Any, SceneWorkerError | None]:
    """A worker's state, or the error it failed to start with (raised by its first job, not at start-up:
    a process pool whose initializer raises only reports a dead process)."""
    try:
        return init(setting), None
    except Exception as err:  # noqa: BLE001  (any failure of the worker's own set-up)
        return None, SceneWorkerError(f"a scene worker failed to start: {_describe(err)}")


def _call(job: Callable[[Any, Any], Any], state: Any, error: SceneWorkerError | None, item: Any) -> Any:
    """``job(state, item)``, its failure (or the worker's start-up failure) as a :class:`SceneWorkerError`."""
    if error is not None:
        raise error
    try:
        return job(state, item)
    except SceneWorkerError:
        raise
    except Exception as err:  # noqa: BLE001  (any failure of the job)
        raise SceneWorkerError(f"a scene worker failed on {item!r:.80}: {_describe(err)}") from err


# ----------------------------------------------------------------------------- local processes


def _in_process(init, setting, job, items: list) -> Iterator[Any]:
    state, error = _start(init, setting)
    try:
        for item in items:
            yield _call(job, state, error, item)
    finally:
        close = getattr(state, "close", None)
        if callable(close):
            close()


_WORKER: dict[str, Any] = {}
"""A spawned worker process's ``state`` and start-up ``error`` (:func:`_start_process`)."""


def _start_process(init: Callable[[Any], Any], setting: Any) -> None:
    _WORKER["state"], _WORKER["error"] = _start(init, setting)


def _run_in_process(job: Callable[[Any, Any], Any], item: Any) -> Any:
    return _call(job, _WORKER["state"], _WORKER["error"], item)


def _local(init, setting, job, items: list, workers: int) -> Iterator[Any]:
    with cf.ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_start_process,
                                initargs=(init, setting)) as pool:
        futures = [pool.submit(_run_in_process, job, item) for item in items]
        try:
            for future in cf.as_completed(futures):
                try:
                    result = future.result()
                except cf.process.BrokenProcessPool as err:
                    raise SceneWorkerError(f"a scene worker process died ({err})") from None
                yield result
        finally:
            for future in futures:
                future.cancel()


# ----------------------------------------------------------------------------- Ray


class _RayWorker:
    """A Ray actor holding one worker's state (made a remote class in :func:`_ray`)."""

    def __init__(self, init: Callable[[Any], Any], setting: Any) -> None:
        self.state, self.error = _start(init, setting)

    def run(self, job: Callable[[Any, Any], Any], item: Any) -> Any:
        return _call(job, self.state, self.error, item)


def _ray(init, setting, job, items: list, workers: int, address: str | None) -> Iterator[Any]:
    try:
        import ray
    except ImportError:
        raise SceneWorkerError('executor "ray" needs Ray: pip install -e ".[ray]"') from None
    started_here = not ray.is_initialized()
    if started_here:
        kwargs = dict(address=address) if address else dict(num_cpus=workers)
        ray.init(include_dashboard=False, log_to_driver=False, **kwargs)
    actor_class = ray.remote(num_cpus=1)(_RayWorker)
    actors = [actor_class.remote(init, setting) for _ in range(workers)]
    try:
        pending: dict[Any, Any] = {}
        queue = list(items)
        idle = list(actors)
        while queue or pending:
            while queue and idle:
                actor = idle.pop()
                pending[actor.run.remote(job, queue.pop(0))] = actor
            done, _ = ray.wait(list(pending), num_returns=1)
            actor = pending.pop(done[0])
            try:
                result = ray.get(done[0])
            except ray.exceptions.RayTaskError as err:
                cause = err.as_instanceof_cause()
                message = str(cause.args[0]) if isinstance(cause, SceneWorkerError) and cause.args else str(err)
                raise SceneWorkerError(message.strip().splitlines()[-1] if message else repr(err)) from None
            except ray.exceptions.RayActorError as err:
                raise SceneWorkerError(f"a scene worker died ({err})") from None
            idle.append(actor)
            yield result
    finally:
        for actor in actors:
            ray.kill(actor)
        if started_here:
            ray.shutdown()


# ----------------------------------------------------------------------------- the entry point


def run_scenes(init: Callable[[Any], Any], setting: Any, job: Callable[[Any, Any], Any], items: Iterable[Any],
               workers: int = 1, executor: str = "local", ray_address: str | None = None) -> Iterator[Any]:
    """Results of ``job(init(setting), item)`` for every item, in the order they finish.

    ``init`` and ``job`` must be module-level functions and ``setting``, the items and the results
    picklable (they cross process boundaries). Raises :class:`SceneWorkerError` when a worker fails.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; expected one of {', '.join(EXECUTORS)}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if ray_address is not None and executor != "ray":
        raise ValueError("ray_address needs executor='ray'")
    items = list(items)
    if not items:
        return iter(())
    if executor == "ray":
        return _ray(init, setting, job, items, int(workers), ray_address)
    if workers == 1:
        return _in_process(init, setting, job, items)
    return _local(init, setting, job, items, min(int(workers), len(items)))
