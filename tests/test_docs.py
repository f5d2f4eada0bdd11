"""The docs hold: every fenced Python block of README.md and docs/*.md runs, every image link
resolves, every gallery row whose picture exists shows it (issue 39).

A block is skipped only when the line right before its fence says why, visibly:
``<!-- no-run: needs a SLURM cluster -->``. The blocks of one file run in order in one
namespace (a later block may use an earlier one's names), in a fresh folder holding links to
the checkout's ``data/`` and ``examples/``, as ``__main__`` of a process of their own.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\s*$")
NO_RUN = re.compile(r"^<!--\s*no-run:\s*(\S.*?)\s*-->$")

#: Runs the blocks of one file: exec each with the file's own line numbers, stop at the first
#: failure naming it. A block may start processes by ``spawn`` (sweeps' Dask workers).
DRIVER = r"""
import json, sys, time, traceback

def main():
    doc, blocks = json.load(open(sys.argv[1]))
    ns = {"__name__": "__main__"}
    for line, code in blocks:
        t0 = time.perf_counter()
        try:
            exec(compile("\n" * line + code, doc, "exec"), ns)
        except BaseException:
            traceback.print_exc()
            print(f"BLOCK FAILED: {doc}:{line}", flush=True)
            sys.exit(1)
        print(f"BLOCK OK: {doc}:{line} {time.perf_counter() - t0:.2f} s", flush=True)

if __name__ == "__main__":  # not in the processes a block spawns
    main()
"""


@dataclass(frozen=True)
class Block:
    """One fenced Python block: the line of its first code line (1-based), its code and the
    reason it does not run (``None``: it runs)."""

    line: int
    code: str
    skip: str | None


def python_blocks(text: str) -> list[Block]:
    """The fenced ``python`` blocks of a markdown text."""
    lines = text.splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        end = next((j for j in range(i + 1, len(lines)) if lines[j].startswith("```")),
                   len(lines))
        if m.group(1) == "python":
            before = lines[i - 1].strip() if i else ""
            skip = NO_RUN.match(before)
            blocks.append(Block(i + 2, "\n".join(lines[i + 1:end]) + "\n",
                                skip.group(1) if skip else None))
        i = end + 1
    return blocks


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


def test_block_parser_and_skip_marker():
    text = ("x\n<!-- no-run: needs a browser -->\n```python\na = 1\n```\n"
            "```bash\nls\n```\n```python\nb = 2\nc = 3\n```\n")
    blocks = python_blocks(text)
    assert blocks == [Block(4, "a = 1\n", "needs a browser"), Block(10, "b = 2\nc = 3\n", None)]


@pytest.mark.parametrize("doc", [d for d in DOCS if python_blocks(d.read_text())],
                         ids=_rel)
def test_python_blocks_run(doc, tmp_path):
    blocks = python_blocks(doc.read_text())
    runnable = [(b.line - 1, b.code) for b in blocks if b.skip is None]
    for b in blocks:  # a skip says why in words, not just a marker
        assert b.skip is None or len(b.skip.split()) >= 2, f"{_rel(doc)}:{b.line}: {b.skip!r}"
    assert len(runnable) * 2 >= len(blocks), f"{_rel(doc)}: most blocks are skipped"
    for name in ("data", "examples"):
        (tmp_path / name).symlink_to(ROOT / name)
    spec = tmp_path / "blocks.json"
    spec.write_text(json.dumps([_rel(doc), runnable]))
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    env = dict(os.environ, OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, str(driver), str(spec)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert proc.stdout.count("BLOCK OK") == len(runnable), proc.stdout


# ------------------------------------------------------------------------------ pictures
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)[^)]*\)|<img[^>]*\bsrc=\"([^\"]+)\"")


def test_image_links_resolve():
    missing = []
    for doc in DOCS:
        for m in IMAGE.finditer(doc.read_text()):
            target = m.group(1) or m.group(2)
            if re.match(r"[a-z]+://", target):
                continue
            if not (doc.parent / target.split("#")[0]).is_file():
                missing.append(f"{_rel(doc)}: {target}")
    assert not missing, missing


def gallery_rows(readme: str) -> dict[str, str]:
    """README's gallery table: scene name (the row's first code span) -> the row's text."""
    section = readme.split("## Gallery", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        m = re.match(r"^\|[^|]*\|\s*`(\w+)`", line)
        if m:
            rows[m.group(1)] = line
    return rows


def test_gallery_rows_show_their_pictures():
    rows = gallery_rows((ROOT / "README.md").read_text())
    assert {"contact_incline", "contact_twisted_bar", "contact_bunny_drop"} <= set(rows)
    for name, row in rows.items():
        png = ROOT / "docs" / "gallery" / f"{name}.png"
        if png.is_file():
            assert f"](docs/gallery/{name}.png)" in row.split("|")[1], row


# ------------------------------------------------------------------------------ key table
def test_key_table_is_the_schemas(tmp_path, capsys):
    """docs/scenes.md's key table is what the schema renders, every integrator included;
    ``--check`` fails on a stale copy and the command rewrites it."""
    import typing

    from fem3d.scene.docs import main as docs_main
    from fem3d.scene.docs import render_key_table, update_markdown
    from fem3d.scene.spec import SimulationSpec

    doc = ROOT / "docs" / "scenes.md"
    text = doc.read_text()
    assert update_markdown(text, render_key_table()) == text, \
        "docs/scenes.md's key table is stale: run `python -m fem3d.scene.docs`"
    row = next(line for line in text.splitlines() if line.startswith("| `simulation.integrator`"))
    for name in typing.get_args(SimulationSpec.model_fields["integrator"].annotation):
        assert f"`{name}`" in row, row
    stale = tmp_path / "scenes.md"
    stale.write_text(text.replace(" \\| `bdf2`", ""))
    assert docs_main(["--check", "--file", str(stale)]) == 1
    assert "+| `simulation.integrator`" in capsys.readouterr().out
    assert docs_main(["--file", str(stale)]) == 0 and stale.read_text() == text
