"""docs/figures/newmark_contact_energy.png: total energy (kinetic + strain + gravity) of the
contact bunny drop (1.5 s) for implicit, bdf2, newmark (with contact: gamma = 0.55, beta =
gamma^2) and newmark with average acceleration (``CONTACT_ALPHA = 0``, what it was before).

Run: ``python scripts/newmark_contact_figure.py`` (a few minutes).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import fem3d.solve.schemes.newmark as newmark_module  # noqa: E402
from fem3d.scene import load_scene  # noqa: E402
from fem3d.simulation import Simulation  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
STEPS = 150


def energies(name: str) -> np.ndarray:
    sim = Simulation(load_scene("contact_bunny_drop", {"simulation.integrator": name}),
                     scripted=True)
    es = [sim.energies()["total"]]
    for _ in range(STEPS):
        sim.step()
        es.append(sim.energies()["total"])
    return np.array(es)


def main() -> None:
    alpha = newmark_module.CONTACT_ALPHA
    curves = {name: energies(name) for name in ("implicit", "bdf2", "newmark")}
    newmark_module.CONTACT_ALPHA = 0.0
    try:
        before = energies("newmark")
    finally:
        newmark_module.CONTACT_ALPHA = alpha
    t = 0.01 * np.arange(STEPS + 1)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, es in curves.items():
        label = f"newmark (contact: gamma = {0.5 + alpha:g})" if name == "newmark" else name
        ax.plot(t, es, label=label)
        print(name, "max", es.max(), "final", es[-1])
    ax.plot(t, before, "k--", label="newmark, average acceleration (gamma = 1/2)")
    print("average acceleration max", before.max(), "final", before[-1])
    ax.set_yscale("symlog", linthresh=10.0)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("total energy (J)")
    ax.set_title("contact_bunny_drop, dt = 0.01")
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = ROOT / "docs" / "figures" / "newmark_contact_energy.png"
    fig.savefig(out, dpi=100)
    print(out)


if __name__ == "__main__":
    main()
