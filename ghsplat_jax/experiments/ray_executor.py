"""Experiment runs as Ray tasks: `ghsplat run EXP.toml --executor ray [--address ADDR]`.

Each (scene, variant) is one task that reserves what a run needs (a GPU when the cluster
has GPUs, else `cpus_per_run` CPUs) and calls the function the runner gives it, the same
`runner.run_one` the local executor calls: finished runs are skipped, interrupted ones resume from their checkpoint, and
every run writes its usual folder. A task whose worker dies (a node lost, memory) is
retried by Ray and resumes from the last checkpoint it wrote.

On a cluster every node needs this package installed and the experiment's output folder
and datasets on a path all nodes share (the driver resolves the output folder to an
absolute path before submitting). Ray is an optional extra: `pip install -e ".[ray]"`.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

log = logging.getLogger("ghsplat.run")


def _task(work: Callable, run) -> str | None:
    """What a Ray worker executes; `work` travels by reference (module and name), so workers
    import the runner themselves."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return work(run)


def resources(cluster: dict, cpus_per_run: float | None = None, gpus_per_run: float | None = None) -> dict:
    """Ray resource request of one run: a whole GPU on clusters that have GPUs, else one CPU,
    unless given explicitly."""
    if gpus_per_run is None:
        gpus_per_run = 1.0 if cluster.get("GPU", 0) > 0 else 0.0
    if cpus_per_run is None:
        cpus_per_run = 1.0
    return {"num_cpus": float(cpus_per_run), "num_gpus": float(gpus_per_run)}


def run_on_ray(runs: list, work: Callable, address: str | None = None, stop_on_error: bool = False,
               cpus_per_run: float | None = None, gpus_per_run: float | None = None,
               max_retries: int = 2) -> list[tuple[str, str]]:
    """Run `work(run)` for each of `runs` (runner.PlannedRun) as Ray tasks; `work` returns None
    or an error text. Returns the failed runs as (scene/variant, message).

    address: None starts a local Ray instance (or uses the one this process already
    started), "auto" joins the cluster this machine belongs to, "ray://HOST:10001" connects
    a client to a remote cluster's head."""
    import ray

    started = not ray.is_initialized()
    if started:
        ray.init(address=address, include_dashboard=False if address is None else None,
                 logging_level=logging.WARNING)
    try:
        need = resources(ray.cluster_resources(), cpus_per_run, gpus_per_run)
        task = ray.remote(_task).options(max_retries=max_retries, **need)
        runs = [dataclasses.replace(r, out_dir=r.out_dir.absolute()) for r in runs]  # workers' cwd differs
        pending = {task.remote(work, r): f"{r.scene}/{r.variant}" for r in runs}
        log.info("submitted %d runs to Ray, each reserving %s", len(pending), need)
        failed = []
        while pending:
            (done,), _ = ray.wait(list(pending), num_returns=1)
            name = pending.pop(done)
            try:
                msg = ray.get(done)
            except Exception as exc:  # the task itself died (RayTaskError, WorkerCrashedError, ...)
                msg = f"{type(exc).__name__}: {exc}"
            if msg is None:
                log.info("%s: done", name)
                continue
            failed.append((name, msg))
            if stop_on_error:
                for ref in pending:
                    ray.cancel(ref)
                break
        return failed
    finally:
        if started:
            ray.shutdown()
