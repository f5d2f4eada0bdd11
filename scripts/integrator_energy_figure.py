"""docs/figures/integrator_energy.png: total energy over time of one undamped scene (a
clamped Neo-Hookean bar set swinging) for implicit, bdf2, newmark and linear.

Run: ``python scripts/integrator_energy_figure.py`` (a few seconds).
"""

from __future__ import annotations

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from fem3d.solve.schemes.registry import SCHEMES  # noqa: E402
from tests.solve.test_bdf2_newmark_static import _energy, bar, set_vibrating  # noqa: E402


def main() -> None:
    model, system, fixed = bar(3)
    dt, n = 0.01, 300
    fig, ax = plt.subplots(figsize=(7, 4))
    for name in ("implicit", "bdf2", "newmark", "linear"):
        s = set_vibrating(model, fixed, 1.0)
        es = [_energy(model, s)]
        try:
            for _ in range(n):
                kw = {} if name == "linear" else {"max_iterations": None}
                s, _ = SCHEMES[name].model_step(system, s, dt, **kw)
                es.append(_energy(model, s))
        except Exception as exc:  # noqa: BLE001 - the unstable scheme stops the curve
            print(name, "stopped:", exc)
        es = np.array(es)
        # linear and implicit lose energy alike here: the dashes keep both curves visible
        ax.plot(dt * np.arange(es.size), es / es[0], label=name,
                linestyle="--" if name == "linear" else "-")
        print(f"{name}: E(end)/E(0) = {es[-1] / es[0]:.6f}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("total energy / initial")
    ax.set_title("undamped Neo-Hookean bar, dt = 0.01")
    ax.legend()
    fig.tight_layout()
    out = ROOT / "docs" / "figures" / "integrator_energy.png"
    fig.savefig(out, dpi=110)
    print("wrote", out)


if __name__ == "__main__":
    main()
