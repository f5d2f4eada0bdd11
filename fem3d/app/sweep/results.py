"""A sweep's results: ``results.csv`` (one row per case, :func:`write_results`) and
``results.png`` (the metric against each swept parameter, :func:`plot_results`)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from fem3d.app.sweep.plan import SweepPlan, _read_summary
from fem3d.app.sweep.spec import METRICS, SweepFile
from fem3d.io.files import atomic_write

__all__ = ["write_results", "plot_results"]


def _rows(plan: SweepPlan, lost: Mapping[str, str]) -> list[dict[str, Any]]:
    rows = []
    cache: dict[str, dict[str, Any] | None] = {}
    for case in plan.cases:
        row: dict[str, Any] = {"case": case.index, "id": case.id}
        row.update({k: case.params.get(k) for k in plan.spec.swept_keys})
        if case.error is not None:
            row.update(status="failed", message=case.error)
            rows.append(row)
            continue
        if case.id not in cache:
            cache[case.id] = _read_summary(plan.out / "cases" / case.id)
        s = cache[case.id]
        if s is None or s.get("digest") != case.digest:
            status = "lost" if case.id in lost else "pending"
            row.update(status=status, message=lost.get(case.id, "not run yet"))
        else:
            row.update(status=s.get("status", "failed"), message=s.get("message", ""))
            row.update(_metrics(s))
            row.update(worker=s.get("worker"), attempt=s.get("attempt"))
        rows.append(row)
    return rows


def _metrics(s: Mapping[str, Any]) -> dict[str, Any]:
    """``results.csv`` metrics from a case summary (the fields of ``RunSummary``)."""
    names = {
        "wall_seconds": ("wall_seconds",),
        "steps": ("steps",),
        "newton_iterations": ("newton_iterations",),
        "kinetic_final": ("kinetic_final", "final_kinetic", "kinetic"),
        "potential_final": ("potential_final", "final_potential", "potential"),
        "total_final": ("total_final", "final_total", "total"),
        "total_max": ("total_max", "max_total", "max_total_energy"),
        "max_displacement": ("max_displacement",),
    }
    out = {}
    for col, keys in names.items():
        out[col] = next((s[k] for k in keys if k in s), None)
    return out


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, list | dict):
        return json.dumps(value)
    return str(value)


def write_results(out: Path, spec: SweepFile, rows: Sequence[Mapping[str, Any]]) -> None:
    """``out/results.csv`` (one row per case) and ``out/results.png`` (the metric against
    each swept parameter), both written atomically."""
    columns = ["case", "id", *spec.swept_keys, "status", "message", *METRICS, "worker",
               "attempt"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in columns])
    atomic_write(out / "results.csv", buf.getvalue())
    plot_results(out / "results.png", spec, rows)


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)


def plot_results(path: Path, spec: SweepFile, rows: Sequence[Mapping[str, Any]]) -> None:
    """One panel per swept key path: ``spec.results.metric`` of each ok case against the
    key's value; failed (or not yet run) cases as red crosses along the bottom."""
    # imported here: pyplot only after choosing the Agg back end (headless), and only when a
    # sweep plots (slow to import)
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # only after choosing the Agg backend

    metric = spec.results.metric
    keys = spec.swept_keys or ["case"]
    ncol = min(3, len(keys))
    nrow = math.ceil(len(keys) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), squeeze=False)
    good = [r for r in rows if r["status"] == "ok" and isinstance(r.get(metric), int | float)]
    bad = [r for r in rows if r not in good]
    ys = [float(r[metric]) for r in good]
    floor = min(ys) if ys else 0.0
    for ax, key in zip(axes.flat, keys, strict=False):
        values = [r.get(key) for r in rows]
        if _numeric([v for v in values if v is not None]):
            pos = lambda r, k=key: r.get(k)  # noqa: E731
            xs = [v for v in values if v is not None]
            if xs and min(xs) > 0 and max(xs) / min(xs) > 30:
                ax.set_xscale("log")
            else:
                ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4))
        else:
            labels = sorted({_cell(v) for v in values}, key=str)
            pos = lambda r, k=key, lab=labels: lab.index(_cell(r.get(k)))  # noqa: E731
            ax.set_xticks(range(len(labels)), labels, rotation=30, ha="right", fontsize=7)
        if good:
            ax.plot([pos(r) for r in good], ys, "o", ms=5, alpha=0.8, label="ok")
        if bad:
            ax.plot([pos(r) for r in bad if r.get(key) is not None or key == "case"],
                    [floor for r in bad if r.get(key) is not None or key == "case"],
                    "x", color="tab:red", ms=7, label="failed / not run")
        ax.tick_params(labelsize=7)
        ax.set_xlabel(key, fontsize=8)
        ax.set_ylabel(metric, fontsize=8)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(keys):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"{spec.name}: {metric} ({len(good)} ok of {len(rows)} cases)", fontsize=10)
    fig.tight_layout()
    try:
        atomic_write(path, lambda p: fig.savefig(p, dpi=110, format="png"))
    finally:
        plt.close(fig)


