"""Run a sweep's runs as Ray tasks (``pip install -e ".[ray]"``).

Each run is one task, ``ray.remote(num_gpus=1)`` on a GPU and ``num_cpus = threads or 1`` on
a CPU; the task starts the same run process as the local backend
(`neus_l0.experiments.runner.run_in_subprocess`), so peak memory stays per run and a crash stays
inside its run. Rows are handed back as tasks finish (`ray.wait`). An already initialised
Ray (``ray.init(address=...)`` by the caller, or a cluster named by ``RAY_ADDRESS``) is used
as it is; otherwise a local instance is started and shut down afterwards.

Signals. Ray's workers cannot pass a signal on to the run process they wait for, so the
sweep stops the runs through their tasks: on SIGTERM / SIGINT (seen through the caller's
`StopOnSignal`) every task is cancelled with ``ray.cancel(force=True)``, which kills its
worker; the run process, its parent gone, stops as on SIGTERM
(`neus_l0.experiments.runner.stop_when_orphaned`: the step ends, the checkpoint is written and the
run records itself interrupted). The runs that had started are recorded interrupted at once,
the others never start.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from neus_l0.errors import NeusL0Error
from neus_l0.experiments.runner import (
    RunSpec,
    failed_row,
    interrupted_row,
    run_in_subprocess,
    write_status,
)
from neus_l0.train.signals import StopOnSignal

#: How often (seconds) the sweep looks for a signal while it waits for the tasks.
POLL_S = 0.5


def _task(spec: RunSpec, timeout: float | None) -> dict:
    return run_in_subprocess(spec, timeout)


def started(spec: RunSpec) -> bool:
    """Whether `spec`'s run process has started and not yet finished: its run folder holds
    the spec.json a start writes (into an emptied folder) but no status.json."""
    return (spec.run_dir / "spec.json").is_file() and not (spec.run_dir / "status.json").exists()


def cancel_tasks(ray, pending: dict, finished: Callable[[dict, str], None], why: str) -> None:
    """Force-cancel every task of `pending` (ref -> spec); record the runs that had started
    as interrupted (`why`: by which signal) and hand their rows to `finished`."""
    for ref in pending:
        ray.cancel(ref, force=True)
    for spec in pending.values():
        if started(spec):
            row = interrupted_row(spec, f"{why} (its Ray task was cancelled; the run "
                                        "checkpoints at its next step)")
            write_status(spec, row)
            finished(row, spec.name)


def _collect(ray, pending: dict, finished: Callable[[dict, str], None],
             stop: StopOnSignal | None) -> None:
    """Hand each task's row to `finished` as it completes (popping it from `pending`, ref ->
    spec), looking for a signal every `POLL_S` seconds; on one, `cancel_tasks`."""
    while pending:
        if stop is not None and stop.requested:
            cancel_tasks(ray, pending, finished, f"stopped by {stop.signal_name}")
            pending.clear()
            return
        done, _ = ray.wait(list(pending), num_returns=1, timeout=POLL_S)
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


def run_with_ray(specs: Sequence[RunSpec], finished: Callable[[dict, str], None],
                 timeout: float | None = None, stop: StopOnSignal | None = None) -> None:
    """Submit every spec as a Ray task and call ``finished(row, name)`` as each completes.

    Args:
        specs: the runs; finished: called with each run's row and name.
        timeout: seconds after which a run's process is killed (None: no limit).
        stop: the caller's active `StopOnSignal`: once it has seen SIGTERM / SIGINT, every
            task is cancelled (see the module notes) and this returns. An exception while
            waiting (a second Ctrl-C) cancels them too.

    Raises:
        NeusL0Error: Ray is not installed.
    """
    try:
        import ray
    except ImportError:
        raise NeusL0Error("--backend ray needs Ray: pip install -e \".[ray]\"") from None
    if not specs:
        return
    started_here = False
    if not ray.is_initialized():
        ray.init(include_dashboard=False, log_to_driver=False)
        started_here = True
    try:
        remote = ray.remote(max_retries=0)(_task)
        pending = {}
        for spec in specs:
            if spec.device == "cuda":
                opts = {"num_gpus": 1, "num_cpus": 1}
            else:
                opts = {"num_cpus": spec.threads or 1}
            pending[remote.options(**opts).remote(spec, timeout)] = spec
        try:
            _collect(ray, pending, finished, stop)
        except BaseException:  # e.g. a second Ctrl-C: do not leave the tasks running
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
    finally:
        if started_here:
            ray.shutdown()
