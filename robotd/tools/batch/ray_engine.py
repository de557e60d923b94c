"""The Ray engine of ``robotd replay-many --ray ADDRESS`` (``pip install 'robotd[cluster]'``).

Ray schedules; robotd only declares. Each job is one Ray task running
:func:`robotd.tools.batch.jobs.run_job`, with its resources declared (``num_cpus=1`` and ``memory``, the
job's memory estimate, so Ray places no more replays on a node than its cores and memory hold) and
``max_retries``: a worker process that dies (killed, crashed, taken by Ray's memory monitor) is
retried by Ray on any node, and only when the retries run out does its row say "died". A replay
that raises is not retried (it would raise again): its row says why, as on the local engine.

``--ray ADDRESS`` joins a running cluster (``ray start --head`` on one machine, ``ray start
--address HEAD:6379`` on the others; ``auto`` for the local one): every node needs the same robotd
installed (a row from a worker with other code says so) and the sources under the same paths
(a shared folder). ``--ray local`` starts a Ray instance on this machine for the run, on loopback,
and stops it at the end. Trajectories come back in the rows, so only the sources need sharing.

This module is imported only when ``--ray`` is given: the local default never imports ray.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from typing import Any

from robotd.core.errors import InputError
from robotd.tools.batch.jobs import DIED, ERROR, INTERRUPTED, MEMORY
from robotd.tools.batch.local import _failed_row

logger = logging.getLogger("robotd.batch.ray_engine")  # its name before the layer packages: users filter by it

TASK_NAME = "robotd_replay"  # Ray shows a worker running one as the process ray::robotd_replay
DEFAULT_MAX_RETRIES = 3


def robotd_replay(job: dict[str, Any]) -> dict[str, Any]:
    """The Ray task: one replay in a Ray worker process."""
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # one core per task (num_cpus=1)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    os.environ["ROBOTD_BATCH_SELF_KILL"] = "1"  # stuck past a limit's grace: end this worker
    from robotd.tools.batch.jobs import run_job

    return run_job(job)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise InputError("--ray: Ray is not installed here: pip install 'robotd[cluster]'") from None
    return ray


class RayEngine:
    """Runs jobs as Ray tasks (module docstring)."""

    name = "ray"

    def __init__(self, address: str, workers: int = 0, max_retries: int = DEFAULT_MAX_RETRIES) -> None:
        self.address = address
        self.workers = workers  # --ray local: the CPUs the local instance offers (0: every core)
        self.max_retries = max_retries
        self.cluster: dict[str, Any] = {}

    def describe(self) -> str:
        cpus = self.cluster.get("CPU")
        where = "a local Ray instance" if self.address == "local" else f"the Ray cluster at {self.address}"
        return f"ray, {where}" + (f" ({cpus:g} CPUs)" if cpus else "")

    def _init(self, ray: Any) -> None:
        kwargs: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}
        try:
            if self.address == "local":
                ray.init(
                    address="local",  # a new instance, even where another one runs (ray start)
                    num_cpus=self.workers or None,
                    include_dashboard=False,
                    _node_ip_address="127.0.0.1",
                    **kwargs,
                )
            else:
                ray.init(address=self.address, **kwargs)
        except Exception as exc:  # ConnectionError, a bad address, ...
            raise InputError(f"--ray {self.address}: {' '.join(str(exc).split())[:500]}") from None
        self.cluster = dict(ray.cluster_resources())

    def run(self, jobs: Sequence[dict[str, Any]], on_row: Callable[[dict[str, Any]], None]) -> None:
        ray = _import_ray()
        self._init(ray)
        refs: dict[Any, dict[str, Any]] = {}
        try:
            task = ray.remote(robotd_replay)
            for job in jobs:
                mem = float(job.get("memory_mb") or 0.0)
                opts: dict[str, Any] = {"num_cpus": 1, "max_retries": self.max_retries, "retry_exceptions": False}
                if mem > 0:
                    opts["memory"] = int(mem * 1e6)
                refs[task.options(**opts).remote(job)] = job
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1, timeout=1.0)
                for ref in done:
                    job = refs.pop(ref)
                    on_row(self._result(ray, ref, job))
        except KeyboardInterrupt:
            for ref, job in refs.items():
                try:
                    ray.cancel(ref, force=True)
                except Exception as exc:
                    logger.debug("cancel: %s", exc)
                on_row(_failed_row(job, INTERRUPTED, "interrupted (Ctrl-C)", 0.0, "ray"))
            raise
        finally:
            ray.shutdown()

    def _result(self, ray: Any, ref: Any, job: dict[str, Any]) -> dict[str, Any]:
        exc_mod = ray.exceptions
        try:
            row: dict[str, Any] = ray.get(ref)
            return row
        except exc_mod.OutOfMemoryError as exc:
            return _failed_row(job, MEMORY, f"Ray's memory monitor ended it: {_one_line(exc)}", 0.0, "ray")
        except (exc_mod.WorkerCrashedError, exc_mod.NodeDiedError) as exc:
            what = f"worker died {self.max_retries + 1} times (Ray retried it {self.max_retries} times)"
            return _failed_row(job, DIED, f"{what}: {_one_line(exc)}", 0.0, "ray")
        except exc_mod.TaskCancelledError:
            return _failed_row(job, INTERRUPTED, "cancelled", 0.0, "ray")
        except exc_mod.RayError as exc:
            return _failed_row(job, ERROR, f"Ray: {_one_line(exc)}", 0.0, "ray")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:500]
