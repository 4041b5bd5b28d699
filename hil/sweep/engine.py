"""Where the trials run: Ray tasks (a local Ray started for the sweep, or a cluster), or one
after another in this process (``--serial``, the only way real hardware is swept).

Each Ray task runs one trial in a worker process of its own with BLAS single-threaded, so the
workers do not fight over the cores; a local Ray listens on loopback only and logs quietly.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any, TypeVar

from hil.errors import HilError, UsageError

SINGLE_THREADED = {name: "1" for name in (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")}

Job = TypeVar("Job")
Row = dict[str, Any]


class RayMissingError(HilError):
    """``hil sweep`` on Ray without Ray installed."""


class RayStartError(HilError):
    """The local Ray of a sweep did not start (its temporary folder unusable, or its processes
    not up in time on an overloaded machine)."""


def import_ray() -> ModuleType:
    """The ``ray`` module, or a one-line error naming the extra that installs it."""
    try:
        import ray
    except ImportError:
        raise RayMissingError("sweeps run on Ray, which is not installed: "
                              "pip install 'hil[sweep]'") from None
    return ray


@dataclass(frozen=True)
class Engine:
    """How to run the trials: ``serial`` in this process, else on Ray at ``address`` (None: a
    local Ray of ``workers`` CPUs started for the sweep; ``auto`` or ``ray://HOST:PORT``: an
    existing cluster, ``workers`` then caps the trials in flight)."""

    workers: int | None = None
    address: str | None = None
    serial: bool = False

    @property
    def name(self) -> str:
        return "serial" if self.serial else "ray"

    def run(self, function: Callable[[Job], Row], jobs: Sequence[Job],
            on_done: Callable[[Row], None]) -> int:
        """Run ``function`` on every job, calling ``on_done`` with each row as it comes (in
        completion order); return the parallelism used."""
        if self.serial:
            for job in jobs:
                on_done(function(job))
            return 1
        ray = import_ray()
        started = start_ray(ray, self.workers, self.address)
        try:
            workers = self.workers or int(ray.cluster_resources().get("CPU", 1))
            run_on_ray(ray, function, jobs, workers, on_done)
            return workers
        finally:
            if started:
                ray.shutdown()


def start_ray(ray: ModuleType, workers: int | None, address: str | None) -> bool:
    """Connect to Ray unless this process already is; True when this call started it."""
    if ray.is_initialized():
        return False
    quiet: dict[str, Any] = {"logging_level": logging.ERROR, "log_to_driver": False}
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if address is None:
        # The local workers inherit the environment of the Ray started here, so they are
        # single-threaded without a runtime_env (which would start new workers for the first
        # tasks instead of using the ones Ray starts with it: seconds per sweep). Ray runs
        # workers at nice 15 by default; here they are the work: nice 0.
        with environment(SINGLE_THREADED):
            try:
                ray.init(num_cpus=workers or os.cpu_count() or 1, include_dashboard=False,
                         _node_ip_address="127.0.0.1", _system_config={"worker_niceness": 0},
                         **quiet)
            except Exception as exc:  # Ray's own: an OSError, or a bare Exception (time-out)
                raise RayStartError(f"the local Ray for the sweep did not start: "
                                    f"{first_line(exc)} (--serial runs the trials without "
                                    "Ray)") from None
        return True
    check_address(address)
    try:
        ray.init(address=address, runtime_env={"env_vars": SINGLE_THREADED}, **quiet)
    except (ConnectionError, ValueError) as exc:  # no cluster; no ray[client] for ray://
        raise UsageError(f"--address {address}: cannot join the Ray cluster: "
                         f"{first_line(exc)}") from None
    return True


def first_line(exc: BaseException) -> str:
    """An exception's message in one line (its type when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


@contextlib.contextmanager
def environment(variables: Mapping[str, str]) -> Iterator[None]:
    """``variables`` set in ``os.environ`` for the time of the block, then as they were."""
    saved = {name: os.environ.get(name) for name in variables}
    os.environ.update(variables)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def check_address(address: str) -> None:
    """``auto`` or ``ray://HOST:PORT``, else a one-line error."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if address == "auto" or (address.startswith("ray://") and sep and host and port.isdigit()):
        return
    raise UsageError(f"--address {address}: expected auto (the cluster this machine is part "
                     "of) or ray://HOST:PORT")


def run_on_ray(ray: ModuleType, function: Callable[[Job], Row], jobs: Sequence[Job],
               workers: int, on_done: Callable[[Row], None]) -> None:
    """At most ``workers`` tasks in flight; a task whose worker died is recorded as failed."""
    task = ray.remote(num_cpus=1, max_retries=0)(function)
    queue = list(jobs)
    pending: dict[Any, Job] = {}
    while queue or pending:
        while queue and len(pending) < workers:
            job = queue.pop(0)
            pending[task.remote(job)] = job
        ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
        for ref in ready:
            job = pending.pop(ref)
            try:
                on_done(ray.get(ref))
            except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory)
                on_done(lost_trial(job, exc))


def lost_trial(job: Any, exc: BaseException) -> Row:
    """The row of a trial whose worker never returned one."""
    message = first_line(exc)
    return {"name": getattr(job, "name", "?"), "params": getattr(job, "params", {}),
            "mcap": getattr(job, "mcap", ""), "status": "failed", "kpis": {},
            "error": f"worker lost: {message}", "trial_s": 0.0}

