"""Where the tasks of a campaign run: a local pool (default) or Ray tasks (``--ray [ADDRESS]``).

A task is a picklable function and its arguments returning a list of result
rows. The local executor runs mission tasks in threads (each run's work is in
its own subprocesses) and render tasks in processes (the renders hold the
GIL). The Ray executor submits each task with the CPUs it needs
(``num_cpus``), keeps a bounded number in flight, and hands the rows back as
the tasks finish. Ray is an optional extra (``pip install hilsim[cluster]``).
"""

from __future__ import annotations

import concurrent.futures as cf
import io
import logging
import multiprocessing
import os
import tarfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

Rows = list[dict[str, Any]]
OnDone = Callable[["Task", Any], None]
OnError = Callable[["Task", BaseException], None]


@dataclass(frozen=True)
class Task:
    label: str
    fn: Callable[..., Any]
    args: tuple[Any, ...]
    cpus: float = 1.0


def local_workers(cpus_per_task: float, requested: int | None) -> int:
    """``--workers`` if given, else the cores divided by what a task needs (at least 1)."""
    if requested is not None:
        return max(1, requested)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, int(cores // max(cpus_per_task, 0.1)))


def run_local(tasks: list[Task], workers: int, processes: bool, on_done: OnDone, on_error: OnError,
              on_abort: Callable[[], None] | None = None) -> None:
    """Run ``tasks`` on ``workers`` threads (or spawned processes); callbacks run in this thread.
    ``on_abort`` runs first when this is interrupted (Ctrl-C): it stops what the tasks started."""
    if not tasks:
        return
    pool: cf.Executor
    if processes and workers > 1:
        # fork (the modules already imported come along) unless threads run here, which fork would not copy
        single = threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods()
        pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork" if single else "spawn"))
    else:
        pool = cf.ThreadPoolExecutor(workers, thread_name_prefix="campaign")
    futures: dict[cf.Future[Any], Task] = {}
    try:
        for t in tasks:
            futures[pool.submit(t.fn, *t.args)] = t
        for fut in cf.as_completed(futures):
            t = futures.pop(fut)
            exc = fut.exception()
            if exc is not None:
                on_error(t, exc)
            else:
                on_done(t, fut.result())
    except BaseException:
        if on_abort is not None:
            on_abort()
        raise
    finally:
        for fut in futures:
            fut.cancel()
        pool.shutdown(wait=True, cancel_futures=True)


def ray_available() -> str | None:
    """None when Ray imports, else why not."""
    try:
        import ray  # noqa: F401
    except ImportError as exc:
        return f"ray is not installed ({exc}); pip install 'hilsim[cluster]'"
    return None


def ray_init(address: str | None, num_cpus: int | None = None) -> bool:
    """Connect to Ray: a local instance on loopback when ``address`` is None, else that cluster.
    True when this call started or joined it (the caller shuts it down), False when Ray was up already."""
    why = ray_available()
    if why:
        raise RuntimeError(why)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")   # no usage report leaves the machine
    if address is None:
        # a local Ray on loopback only: with "clusters" off Ray takes 127.0.0.1 as the node address and
        # binds its servers (GCS, raylet, workers, agents) there instead of on every interface
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    import ray
    from ray._private import ray_constants

    if ray.is_initialized():
        return False
    if address is None:
        ray_constants.ENABLE_RAY_CLUSTER = False   # read when Ray picks the node's address
        ray.init(num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1",
                 log_to_driver=False, logging_level=logging.WARNING)
        # let the local workers finish starting (a few seconds of CPU) before the first run competes with them
        cpus = int(ray.cluster_resources().get("CPU", 1))
        noop = ray.remote(_noop)
        ray.get([noop.options(num_cpus=1).remote() for _ in range(max(1, cpus))])
    else:
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    return True


def ray_shutdown() -> None:
    import ray

    ray.shutdown()


def _noop() -> None:
    return None


def run_ray(tasks: list[Task], on_done: OnDone, on_error: OnError, max_in_flight: int = 256) -> None:
    """Run ``tasks`` as Ray tasks (``ray_init`` first), ``num_cpus`` each; callbacks run in this thread."""
    import ray

    remote = ray.remote(_call)
    pending: dict[Any, Task] = {}
    queue = list(reversed(tasks))
    try:
        while queue or pending:
            while queue and len(pending) < max_in_flight:
                t = queue.pop()
                ref = remote.options(num_cpus=t.cpus, max_retries=0, name=t.label[:60]).remote(t.fn, t.args)
                pending[ref] = t
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                t = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - a task's failure is recorded, the campaign goes on
                    on_error(t, exc)
                else:
                    on_done(t, result)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def _call(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    return fn(*args)


def pack(folder: Path, exclude: tuple[str, ...] = ()) -> bytes:
    """A folder as gzip'd tar bytes (regular files and folders; ptys, sockets and links left out)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for p in sorted(folder.rglob("*")):
            rel = p.relative_to(folder)
            if rel.parts[0] in exclude or p.is_symlink() or not (p.is_file() or p.is_dir()):
                continue
            tar.add(p, arcname=str(rel), recursive=False)
    return buf.getvalue()


def unpack(data: bytes, dest: Path) -> None:
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(dest, filter="data")
