"""Run a sweep's runs as Ray tasks (``pip install -e ".[ray]"``).

Each run is one task, ``ray.remote(num_gpus=1)`` on a GPU and ``num_cpus = threads or 1`` on
a CPU; the task starts the same run process as the local backend
(`neus_l0.bench.runner.run_in_subprocess`), so peak memory stays per run and a crash stays
inside its run. Rows are handed back as tasks finish (`ray.wait`). An already initialised
Ray (``ray.init(address=...)`` by the caller, or a cluster named by ``RAY_ADDRESS``) is used
as it is; otherwise a local instance is started and shut down afterwards.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from neus_l0.bench.runner import RunSpec, failed_row, run_in_subprocess, write_status
from neus_l0.errors import NeusL0Error


def _task(spec: RunSpec, timeout: float | None) -> dict:
    return run_in_subprocess(spec, timeout)


def run_with_ray(specs: Sequence[RunSpec], finished: Callable[[dict, str], None],
                 timeout: float | None = None) -> None:
    """Submit every spec as a Ray task and call ``finished(row, name)`` as each completes.

    Raises:
        NeusL0Error: Ray is not installed.
    """
    try:
        import ray
    except ImportError:
        raise NeusL0Error("--backend ray needs Ray: pip install -e \".[ray]\"") from None
    if not specs:
        return
    started = False
    if not ray.is_initialized():
        ray.init(include_dashboard=False, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(max_retries=0)(_task)
        pending = {}
        for spec in specs:
            if spec.device == "cuda":
                opts = {"num_gpus": 1, "num_cpus": 1}
            else:
                opts = {"num_cpus": spec.threads or 1}
            pending[remote.options(**opts).remote(spec, timeout)] = spec
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                spec = pending.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception as exc:  # the task itself failed (worker lost, ...)
                    msg = str(exc).splitlines()[0] if str(exc) else ""
                    row = failed_row(spec, f"Ray task failed: {type(exc).__name__}: {msg}")
                    spec.run_dir.mkdir(parents=True, exist_ok=True)
                    write_status(spec, row)
                finished(row, spec.name)
    finally:
        if started:
            ray.shutdown()
