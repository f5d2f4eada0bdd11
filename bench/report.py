"""Benchmark records (JSON lines) -> Markdown report with ratios, and a log-log plot."""

from __future__ import annotations

import json
import math
import os
import platform
import re
import subprocess
from collections import defaultdict
from collections.abc import Iterable
from importlib import metadata
from pathlib import Path

from bench import CASES, GROUPS

#: Packages whose versions the report lists (distribution names).
PACKAGES = ("numpy", "scipy", "fem3d", "scikit-sparse", "pypardiso", "mkl", "warp-lang",
            "pbatoolkit", "psutil", "threadpoolctl", "matplotlib")

#: Libraries that compute exactly the classic Neo-Hookean (their check values must agree).
SAME_MODEL_PREFIXES = ("fem3d-c", "fem3d-numpy", "numpy-baseline", "warp-cpu")


# ------------------------------------------------------------------------------ environment
def machine_info() -> dict:
    """CPU model, cores, memory, OS, BLAS of NumPy and of CHOLMOD."""
    info: dict = {"platform": platform.platform(), "python": platform.python_version()}
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        m = re.search(r"^Model name:\s*(.+)$", out, re.M)
        info["cpu"] = m.group(1).strip() if m else platform.processor()
    except (OSError, subprocess.SubprocessError):
        info["cpu"] = platform.processor()
    info["cores"] = os.cpu_count()
    try:
        info["cores_available"] = len(os.sched_getaffinity(0))
    except AttributeError:
        pass
    try:
        with open("/proc/meminfo") as f:
            kb = int(re.search(r"MemTotal:\s*(\d+)", f.read()).group(1))
        info["memory_gib"] = round(kb / 2**20, 1)
    except (OSError, AttributeError):
        pass
    try:
        import numpy  # noqa: F401
        from threadpoolctl import threadpool_info

        info["blas"] = sorted({
            f"{d.get('internal_api')} {d.get('version')} ({d.get('num_threads')} threads, "
            f"{Path(d.get('filepath', '')).name})" for d in threadpool_info()
            if d.get("user_api") == "blas"
        })
    except ImportError:
        pass
    blas = Path("/usr/lib/x86_64-linux-gnu/libblas.so.3")
    if blas.exists():
        info["system_libblas"] = os.path.realpath(blas)  # what CHOLMOD (Debian) links
    return info


def versions() -> dict:
    out = {}
    for pkg in PACKAGES:
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    try:
        out["git"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                    text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        out["git"] = None
    return out


# ---------------------------------------------------------------------------------- records
def read_jsonl(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def write_jsonl(path: Path, records: Iterable[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def merge(old: list[dict], new: list[dict]) -> list[dict]:
    """Records of ``new`` replace those of ``old`` with the same (case, size)."""
    key = {(r.get("case"), r.get("size")) for r in new}
    return [r for r in old if (r.get("case"), r.get("size")) not in key] + new


def _fmt_time(t: float) -> str:
    if t < 1e-3:
        return f"{t * 1e6:.0f} us"
    if t < 1.0:
        return f"{t * 1e3:.3g} ms"
    return f"{t:.3g} s"


def _fmt_ratio(r: float) -> str:
    return f"{r:.2g}x" if r < 10 else f"{r:.0f}x"


def _reference_library(group: str, libs: Iterable[str], default_solver: str | None) -> str | None:
    """The fem3d row the group's ratios refer to (its default configuration)."""
    libs = list(libs)
    prefs = ["fem3d-c", "fem3d-numpy", "fem3d-c implicit Euler", "fem3d-numpy implicit Euler"]
    if default_solver:
        prefs.insert(0, f"fem3d-linsolve-{default_solver}")
    prefs += ["fem3d-linsolve-cholmod", "fem3d-linsolve-pardiso", "fem3d-linsolve-superlu"]
    for p in prefs:
        if p in libs:
            return p
    fem = [lib for lib in libs if lib.startswith("fem3d")]
    if fem:
        return fem[0]
    return "numpy-baseline" if "numpy-baseline" in libs else None


def _size_label(size: float) -> str:
    e = math.log10(size)
    return f"1e{e:.0f}" if abs(e - round(e)) < 1e-9 else f"{size:g}"


def render_markdown(records: list[dict], meta: dict, stat: str = "median") -> str:
    """The docs/benchmarks.md text; ``stat`` is ``"median"`` or ``"min"`` of the timed calls."""
    key = f"{stat}_s"
    ok = [r for r in records if r.get("status") == "ok"]
    sizes = sorted({r["size"] for r in records})
    tets = {r["size"]: r.get("n_tets") for r in records if r.get("n_tets")}
    dofs = {r["size"]: r.get("n_dofs") for r in records if r.get("n_dofs")}
    default_solver = meta.get("default_solver")
    lines = [
        "# fem3d benchmarks",
        "",
        "Generated by `python -m bench` (see `bench/README.md`); do not edit by hand.",
        f"Every cell is the **{stat} wall time** of repeated calls after one warm-up call, each "
        "(case, size) in its own process; in parentheses the **ratio to the fem3d row** of the "
        "same table (marked **ref**): above 1x is slower than fem3d.",
        "",
        "## Machine and software",
        "",
    ]
    mi = meta.get("machine", {})
    lines.append(f"- CPU: {mi.get('cpu')}, {mi.get('cores')} cores "
                 f"({mi.get('cores_available', '?')} available), {mi.get('memory_gib')} GiB")
    lines.append(f"- OS: {mi.get('platform')}, Python {mi.get('python')}")
    for b in mi.get("blas", []):
        lines.append(f"- BLAS loaded by the runner (NumPy, SciPy, MKL via pypardiso): {b}")
    if mi.get("system_libblas"):
        lines.append(f"- system libblas.so.3 (CHOLMOD's BLAS): `{mi['system_libblas']}`")
    vers = meta.get("versions", {})
    lines.append("- versions: " + ", ".join(f"{k} {v}" for k, v in vers.items()
                                         if v and k != "git"))
    commits = sorted({r["git"] for r in records if r.get("git")})
    if commits:
        lines.append(f"- measured at commit(s): {', '.join(commits)}")
    if default_solver:
        lines.append(f"- fem3d.solve.linear default (`auto`) back end here: **{default_solver}**")
    cmds = sorted({r.get("command", "") for r in records if r.get("command")})
    for c in cmds:
        lines.append(f"- command: `{c}`")
    loads = [r["loadavg_1m"] for r in ok if "loadavg_1m" in r]
    if loads:
        cores = mi.get("cores_available") or mi.get("cores") or 1
        warn = (" **(above the core count: other processes competed for the CPU; "
                "treat small differences as noise)**" if max(loads) > cores else "")
        lines.append(f"- 1-minute load average at the end of each case: "
                     f"{min(loads):.1f} .. {max(loads):.1f}{warn}")
    dates = sorted({r.get("date", "") for r in records if r.get("date")})
    if dates:
        lines.append(f"- measured: {dates[0]} .. {dates[-1]}" if len(dates) > 1
                     else f"- measured: {dates[0]}")
    summary = Path(__file__).with_name("summary.md")
    if summary.exists():  # hand-written reading of the numbers, kept beside the code
        lines += ["", summary.read_text().strip()]
    lines += ["", "Mesh sizes: a unit box, n x n x n cubes of 6 tets each:", ""]
    lines.append("| size | tets | free DOFs of the solver system |")
    lines.append("| --- | ---: | ---: |")
    for s in sizes:
        t = tets.get(s)
        lines.append(f"| {_size_label(s)} | {t:,} | {dofs.get(s, '')} |" if t else
                     f"| {_size_label(s)} | | |")
    lines.append("")

    by_group: dict[str, dict[str, dict[float, dict]]] = defaultdict(lambda: defaultdict(dict))
    for r in ok:
        by_group[r["group"]][r["library"]][r["size"]] = r
    for group, caption in GROUPS.items():
        rows = by_group.get(group)
        if not rows:
            continue
        ref = _reference_library(group, rows, default_solver)
        threads = sorted({str(r.get("threads") or "default") for lib in rows
                          for r in rows[lib].values()})
        lines += [f"## {group}", "", f"{caption}. Threads: {', '.join(threads)}.", ""]
        hdr = "| library | " + " | ".join(f"{_size_label(s)} ({tets.get(s, 0):,} tets)"
                                           for s in sizes) + " |"
        lines += [hdr, "| --- |" + " ---: |" * len(sizes)]
        order = sorted(rows, key=lambda lib: (lib != ref, not lib.startswith("fem3d"), lib))
        for lib in order:
            cells = []
            for s in sizes:
                r = rows[lib].get(s)
                if r is None:
                    cells.append("")
                    continue
                cell = _fmt_time(r[key])
                rr = rows.get(ref, {}).get(s) if ref else None
                if lib == ref:
                    cell += " (**ref**)"
                elif rr:
                    cell += f" ({_fmt_ratio(r[key] / rr[key])})"
                cells.append(cell)
            lines.append(f"| {lib} | " + " | ".join(cells) + " |")
        lines.append("")
        # agreement of rows computing the same model
        if group in ("energy", "gradient", "hessian_elements", "hessian_csr"):
            worst = 0.0
            for s in sizes:
                vals = [rows[lib][s]["check"] for lib in rows
                        if lib.startswith(SAME_MODEL_PREFIXES) and s in rows[lib]
                        and rows[lib][s].get("check") is not None]
                if len(vals) > 1:
                    worst = max(worst, (max(vals) - min(vals)) / max(abs(max(vals)), 1e-300))
            lines.append(f"Rows computing the classic Neo-Hookean agree to {worst:.1e} "
                         "(relative spread of the output's norm).")
            lines.append("")

    # memory
    lines += ["## Peak memory", "",
              "MiB. First the memory the timed calls themselves need: their peak resident "
              "memory above the process's resident memory after setup (Linux `VmHWM`, reset "
              "after setup). In parentheses the whole worker process's peak (`getrusage` "
              "maxrss: interpreter, libraries, mesh, setup and calls).", ""]
    lines.append("| case | " + " | ".join(_size_label(s) for s in sizes) + " |")
    lines.append("| --- |" + " ---: |" * len(sizes))
    by_case: dict[str, dict[float, dict]] = defaultdict(dict)
    for r in ok:
        by_case[r["case"]][r["size"]] = r
    for case in sorted(by_case, key=lambda c: (list(GROUPS).index(c.split("/")[0])
                                              if c.split("/")[0] in GROUPS else 99, c)):
        cells = []
        for s in sizes:
            r = by_case[case].get(s)
            if r is None:
                cells.append("")
            elif r.get("call_extra_mb") is not None:
                cells.append(f"{r['call_extra_mb']:.0f} ({r['peak_rss_mb']:.0f})")
            else:
                cells.append(f"? ({r['peak_rss_mb']:.0f})")
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    lines.append("")

    # notes, skips, errors
    notes = sorted({CASES[r["case"]].note for r in records
                    if r["case"] in CASES and CASES[r["case"]].note})
    skipped = sorted({(r["case"], r.get("reason", "")) for r in records
                      if r.get("status") == "skip"})
    errors = sorted({(r["case"], _size_label(r["size"]), r.get("reason", ""))
                     for r in records if r.get("status") in ("error", "timeout")})
    if notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    if skipped:
        lines += ["## Skipped", ""]
        lines += [f"- `{c}`: {reason}" for c, reason in skipped]
        lines.append("")
    if errors:
        lines += ["## Failed or timed out", ""]
        lines += [f"- `{c}` at {s}: {reason}" for c, s, reason in errors]
        lines.append("")
    lines += ["![time vs tets](benchmarks.png)", ""]
    return "\n".join(lines)


def render_plot(records: list[dict], path: Path, stat: str = "median") -> None:
    """Log-log time vs tets, one panel per group; fem3d rows solid, peers dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in records if r.get("status") == "ok"]
    groups = [g for g in GROUPS if any(r["group"] == g for r in ok)]
    if not groups:
        return
    ncol = min(4, len(groups))
    nrow = math.ceil(len(groups) / ncol)
    from matplotlib.ticker import NullFormatter

    all_libs = sorted({r["library"] for r in ok})
    cmap = plt.get_cmap("tab20" if len(all_libs) > 10 else "tab10")
    color = {lib: cmap(i % cmap.N) for i, lib in enumerate(all_libs)}  # same colour everywhere
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.6 * nrow), squeeze=False)
    for ax, g in zip(axes.ravel(), groups, strict=False):
        libs = sorted({r["library"] for r in ok if r["group"] == g})
        for lib in libs:
            pts = sorted((r["n_tets"], r[f"{stat}_s"]) for r in ok
                         if r["group"] == g and r["library"] == lib)
            x, y = zip(*pts, strict=True)
            ax.loglog(x, y, "-o" if lib.startswith("fem3d") else "--s", label=lib, ms=4,
                      color=color[lib])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(g)
        ax.set_xlabel("tets")
        ax.set_ylabel(f"seconds ({stat})")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(groups):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
