"""Running a sweep on Dask distributed: :func:`run_case` (one case, the body of each Dask
task, in a worker process) and :func:`run_sweep` (one task per case to run: an embedded
``LocalCluster`` with single-threaded worker processes, or an existing scheduler; a progress
bar; fault tolerance: a worker that dies has its case rescheduled elsewhere by the scheduler;
then ``results.csv`` and ``results.png``).

Each case runs the code of ``fem3d run`` (:func:`fem3d.app.run.run_scene`). Dask
(``dask``, ``distributed``) is an optional dependency (``fem3d[sweep]``): it is imported in
the functions that use it, so that ``fem3d`` and the sweep's planning work without it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
import socket
import sys
import time
import traceback
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tqdm import tqdm

from fem3d.app.run import run_scene
from fem3d.app.sweep.plan import (
    LOG_NAME,
    SCENE_NAME,
    STARTED_NAME,
    SUMMARY_NAME,
    Case,
    SweepPlan,
    _json_safe,
)
from fem3d.app.sweep.results import _rows, write_results
from fem3d.errors import Fem3dError, InputError
from fem3d.io.dataset import write_case_trajectory
from fem3d.io.files import atomic_write
from fem3d.scene.spec import Scene

__all__ = ["THREAD_ENV", "SweepReport", "run_case", "run_sweep"]

#: Environment of every worker process of the embedded cluster: one BLAS / OpenMP thread,
#: set before the process starts (the Nanny's ``env``), so parallelism comes from the cases.
THREAD_ENV: dict[str, str] = {
    name: "1"
    for name in (
        "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
        "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS",
    )
}


# --------------------------------------------------------------------------------------
# glue to the scenes layer (fem3d.scene.spec / fem3d.app.run.run_scene): every use is here


def _scene_from_dict(d: Mapping[str, Any]) -> Any:
    return Scene.from_dict(dict(d))


def _run_scene(scene: Any, out: Path) -> dict[str, Any]:
    """Run ``scene`` into ``out`` with the code of ``fem3d run``; the RunSummary as a dict."""
    summary = run_scene(scene, out, quiet=True, preview=False)
    return dataclasses.asdict(summary)


# --------------------------------------------------------------------------------------
# one case (runs in a worker process)


def _write_json(path: Path, data: Any) -> None:
    atomic_write(path, json.dumps(data, indent=1, allow_nan=False, default=str) + "\n")


def _worker_address() -> str | None:
    try:
        from distributed import get_worker  # optional dependency (fem3d[sweep])

        return str(get_worker().address)
    except (ImportError, ValueError):
        return None


def run_case(task: Mapping[str, Any]) -> dict[str, Any]:
    """Run one case into its folder; the body of each Dask task.

    Clears the folder (a partial earlier attempt), writes ``started.json`` and
    ``scene.json``, runs the scene with the code of ``fem3d run``, writes
    ``trajectory.npz`` in dataset mode, and last, atomically, ``summary.json``. A case
    that fails (bad parameter, explosion) is recorded as failed, never raised: only a dying
    process leaves the folder without ``summary.json``.

    Parameters
    ----------
    task : dict
        ``dir`` (the case folder), ``id``, ``digest``, ``params``, ``scene`` (the resolved
        scene's ``to_dict()``), ``dataset`` (None or ``{"dtype": ...}``).

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """
    case_dir = Path(task["dir"])
    attempt = 1
    if case_dir.exists():  # a partial earlier attempt (its process died): start afresh
        with contextlib.suppress(OSError, ValueError, TypeError, AttributeError):
            earlier = json.loads((case_dir / STARTED_NAME).read_text(encoding="utf-8"))
            attempt = int(earlier.get("attempt", 1)) + 1
        shutil.rmtree(case_dir)
    case_dir.mkdir(parents=True)
    started = {
        "id": task["id"], "attempt": attempt, "host": socket.gethostname(), "pid": os.getpid(),
        "worker": _worker_address(), "started": time.time(),
        "threads": {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")},
    }
    _write_json(case_dir / STARTED_NAME, started)
    _write_json(case_dir / SCENE_NAME, task["scene"])
    t0 = time.perf_counter()
    record: dict[str, Any] = {"status": "failed", "message": ""}
    try:
        scene = _scene_from_dict(task["scene"])
        digest = scene.digest()
        if digest != task["digest"]:
            raise InputError(
                "the scene's mesh files differ on this worker from the ones the sweep was "
                f"planned with (digest {digest[:16]} != {task['id']})"
            )
        with open(case_dir / LOG_NAME, "w", encoding="utf-8") as log, \
                contextlib.redirect_stderr(log), contextlib.redirect_stdout(log):
            record.update(_run_scene(scene, case_dir))
        if task.get("dataset") and record.get("status") == "ok":
            write_case_trajectory(case_dir, dtype=task["dataset"]["dtype"],
                                  meta={"id": task["id"], "params": task["params"]})
    except Fem3dError as exc:
        record.update(status="failed", message=str(exc))
    except Exception as exc:  # an unexpected error: recorded, with its traceback beside it
        record.update(status="failed", message=f"{type(exc).__name__}: {exc}")
        (case_dir / "error.txt").write_text(traceback.format_exc(), encoding="utf-8")
    summary = {
        "id": task["id"], "digest": task["digest"], "params": task["params"],
        **_json_safe(record),
        "case_seconds": time.perf_counter() - t0, "attempt": attempt,
        "worker": started["worker"], "host": started["host"], "pid": started["pid"],
        "threads": started["threads"], "finished": time.time(),
    }
    _write_json(case_dir / SUMMARY_NAME, summary)
    return summary


# --------------------------------------------------------------------------------------
# the engine


@dataclasses.dataclass
class SweepReport:
    """What an invocation did.

    Attributes
    ----------
    rows : list of dict
        One per case, in sweep order (the rows of ``results.csv``).
    ran, skipped : int
        Cases that ran to an end now (ok, failed or lost) / complete before.
    lost : list of str
        Ids of cases whose workers kept dying (left partial; the next invocation retries).
    interrupted : bool
    """

    rows: list[dict[str, Any]]
    ran: int
    skipped: int
    lost: list[str]
    interrupted: bool = False

    def count(self, status: str) -> int:
        return sum(1 for r in self.rows if r["status"] == status)


def _open_client(workers: int | None, scheduler: str | None, stack: contextlib.ExitStack):
    # Dask is an optional dependency (fem3d[sweep]): imported where a sweep runs
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return stack.enter_context(Client(scheduler, timeout="20s"))
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    # a task whose worker dies is rescheduled; after this many deaths it is given up (lost)
    stack.enter_context(dask.config.set({"distributed.scheduler.allowed-failures": 3}))
    cluster = stack.enter_context(LocalCluster(
        n_workers=workers or _cores(), threads_per_worker=1, processes=True,
        dashboard_address=None,  # no dashboard; its HTTP server on a free local port
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.CRITICAL, env=dict(THREAD_ENV),
    ))
    return stack.enter_context(Client(cluster))


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _task(plan: SweepPlan, case: Case) -> dict[str, Any]:
    ds = plan.spec.dataset
    return {
        "dir": str((plan.out / "cases" / case.id).resolve()), "id": case.id,
        "digest": case.digest, "params": _json_safe(case.params), "scene": case.scene,
        "dataset": None if ds is None else {"dtype": ds.dtype},
    }


def run_sweep(
    plan: SweepPlan,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    quiet: bool = False,
) -> SweepReport:
    """Run the incomplete cases of ``plan`` on Dask and write the results.

    Parameters
    ----------
    plan : SweepPlan
        From :func:`plan_sweep`.
    workers : int, optional
        Worker processes of the embedded ``LocalCluster`` (default: one per core).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``) instead.
    quiet : bool
        No progress bar.

    Returns
    -------
    SweepReport
    """
    out = plan.out
    (out / "cases").mkdir(parents=True, exist_ok=True)
    _write_json(out / "sweep.json", {
        "name": plan.spec.name, "spec": plan.spec.model_dump(mode="json"),
        "keys": plan.spec.swept_keys,
        "cases": [{"index": c.index, "id": c.id, "params": _json_safe(c.params),
                   "error": c.error} for c in plan.cases],
    })
    lost: dict[str, str] = {}
    interrupted = False
    ran = 0
    if plan.todo:
        from distributed import as_completed  # optional dependency (fem3d[sweep])

        with contextlib.ExitStack() as stack:
            client = _open_client(workers, scheduler, stack)
            token = uuid.uuid4().hex[:8]
            futures = {
                client.submit(run_case, _task(plan, c), key=f"fem3d-case-{c.id}-{token}",
                              pure=False, retries=1): c
                for c in plan.todo
            }
            try:  # distributed >= 2025 lists only 5 workers unless asked for all
                info = client.scheduler_info(n_workers=-1)
            except TypeError:
                info = client.scheduler_info()
            n_workers = len(info.get("workers", {}))
            bar = tqdm(total=len(futures), unit="case", disable=quiet or None,
                       file=sys.stderr, dynamic_ncols=True,
                       desc=f"{plan.spec.name} ({n_workers} workers)")
            done = failed = 0
            try:
                for fut in as_completed(futures):
                    case = futures[fut]
                    if fut.status == "finished":
                        ok = fut.result().get("status") == "ok"
                    else:  # KilledWorker after allowed-failures deaths, or a lost task
                        ok = False
                        exc = fut.exception()
                        why = " ".join(str(exc).split())[:300]
                        lost[case.id] = f"lost: {type(exc).__name__}: {why}"
                    done += ok
                    failed += not ok
                    ran += 1
                    bar.update(1)
                    bar.set_postfix_str(
                        f"done {done} failed {failed} remaining {len(futures) - done - failed}",
                        refresh=True,
                    )
            except KeyboardInterrupt:
                interrupted = True
            finally:
                bar.close()
                if interrupted:
                    client.cancel(list(futures), force=True)
    rows = _rows(plan, lost)
    write_results(out, plan.spec, rows)
    return SweepReport(rows=rows, ran=ran, skipped=len(plan.done),
                       lost=sorted(lost), interrupted=interrupted)


