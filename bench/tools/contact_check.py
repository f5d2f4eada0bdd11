"""Every contact gallery scene run for its whole duration, each step's state checked.

    python -m bench.tools.contact_check                           # every data/scenes/contact_*.toml
    python -m bench.tools.contact_check contact_stack contact_fold --steps 50
    python -m bench.tools.contact_check contact_pile --set contact.self_contact=false

Each scene runs as :class:`fem3d.simulation.Simulation` steps it (the scene file's settings,
one thread). After every step its state is checked by a test of its own, built from the
positions alone (not the solver's contact set, filter or candidates):

* no two triangles intersect: a fresh ``ipctk.CollisionMesh`` of the bodies' boundary
  triangles *and* the mesh obstacles' triangles at that time, all in one group (so a body's
  own surface crossing itself counts), and ``ipctk.has_intersections``;
* no vertex is behind a plane obstacle (its signed distance is positive);
* bodies that start inside the mesh obstacles' bounding box (an open box, a bowl) stay inside
  it: strictly inside its side walls' range and above its floor;
* the kinetic energy: its peak, its value at the end, and the first step from which it stays
  below ``--rest`` (default 1e-6) of the peak. Scenes listed in :data:`COMES_TO_REST` must
  get there; the others (a block sliding down an incline, a bar twisted by its pins) print it.
  A run not at rest at the end names its last stretch at rest, if it had one (a pile that
  settled and then slipped), and the bodies still moving faster than :data:`MOVING`.

Prints one line per scene and exits 1 when a check fails. ``python -m bench.tools.pile_check`` is
the pile's run through ``fem3d run`` with its frames checked the same way.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "data" / "scenes"

#: gallery scenes whose bodies must come to rest within their duration
COMES_TO_REST = {"contact_bunny_drop", "contact_pile"}


@dataclass
class StateChecks:
    """Running checks of a sequence of states (see the module)."""

    faces: np.ndarray  # the bodies' boundary triangles
    planes: list[tuple[np.ndarray, np.ndarray]]  # (point, unit normal)
    box: tuple[np.ndarray, np.ndarray] | None  # mesh obstacles' bounds, when bodies start inside
    states: int = 0
    intersecting: list[int] = field(default_factory=list)
    behind_plane: list[int] = field(default_factory=list)
    outside_box: list[int] = field(default_factory=list)
    min_plane_gap: float = np.inf
    min_box_clearance: float = np.inf

    def add(self, x: np.ndarray, obstacles: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Check positions ``x`` (n, 3) with the mesh obstacles ``(vertices, faces)`` then."""
        import ipctk

        k = self.states
        self.states += 1
        V, F = [np.asarray(x, dtype=np.float64)], [self.faces]
        offset = len(x)
        for ov, of in obstacles:
            V.append(np.asarray(ov, dtype=np.float64))
            F.append(np.asarray(of, dtype=np.int64) + offset)
            offset += len(ov)
        V = np.asfortranarray(np.concatenate(V))
        F = np.ascontiguousarray(np.concatenate(F), dtype=np.int32)
        if ipctk.has_intersections(ipctk.CollisionMesh(V, ipctk.edges(F), F), V):
            self.intersecting.append(k)
        for point, normal in self.planes:
            gap = float(((x - point) @ normal).min())
            self.min_plane_gap = min(self.min_plane_gap, gap)
            if gap <= 0.0:
                self.behind_plane.append(k)
        if self.box is not None:
            c = box_clearance(x, *self.box)
            self.min_box_clearance = min(self.min_box_clearance, c)
            if c <= 0.0:
                self.outside_box.append(k)

    @property
    def ok(self) -> bool:
        return not (self.intersecting or self.behind_plane or self.outside_box)


def box_clearance(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """Smallest distance of a point of ``x`` to the box's side walls (x, z) and floor (y);
    positive inside."""
    return min(float((x[:, 0] - lower[0]).min()), float((upper[0] - x[:, 0]).min()),
               float((x[:, 2] - lower[2]).min()), float((upper[2] - x[:, 2]).min()),
               float((x[:, 1] - lower[1]).min()))


#: a body whose fastest vertex is faster than this (m/s) at the end is named as moving
MOVING = 1e-3


def rest_step(kinetic: np.ndarray, rel: float) -> int | None:
    """First step from which ``kinetic`` stays below ``rel`` times its peak (None: never)."""
    below = kinetic < rel * kinetic.max()
    if not below[-1]:
        return None
    above = np.flatnonzero(~below)
    return int(above[-1] + 1) if above.size else 0


def last_rest(kinetic: np.ndarray, rel: float, at_least: int = 10) -> tuple[int, int] | None:
    """The last stretch of ``at_least`` or more states below ``rel`` times the peak that ends
    before the last state, ``(first, last)`` (None: none, or the run ends at rest): a pile
    that came to rest and then slipped."""
    below = np.concatenate([[False], kinetic < rel * kinetic.max(), [False]])
    starts = np.flatnonzero(~below[:-1] & below[1:])
    ends = np.flatnonzero(below[:-1] & ~below[1:]) - 1
    runs = [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)
            if b - a + 1 >= at_least and b < len(kinetic) - 1]
    return runs[-1] if runs else None


def scene_checks(sim) -> StateChecks:
    """The checks for a :class:`~fem3d.simulation.Simulation`'s scene (planes, the box)."""
    from fem3d.mesh.tetmesh import boundary_faces

    cm = sim.contact.contact
    planes = [(np.asarray(p.point, float), np.asarray(p.normal, float)
               / np.linalg.norm(p.normal)) for p in cm.planes]
    box = None
    if cm.meshes:
        V = np.concatenate([m.positions(0.0) for m in cm.meshes])
        lower, upper = V.min(axis=0), V.max(axis=0)
        if box_clearance(sim.q, lower, upper) > 0.0:
            box = (lower, upper)
    return StateChecks(boundary_faces(sim.model.T).astype(np.int64), planes, box)


def run_and_check(scene, steps: int | None = None) -> tuple[StateChecks, np.ndarray, dict]:
    """Step ``scene`` (its duration, or ``steps``) and check every state; returns the
    checks, the kinetic energy per state and figures (timing, Newton iterations, the fastest
    vertex's speed at the end)."""
    from fem3d.simulation import Simulation

    sim = Simulation(scene)
    n = steps if steps is not None else round(scene.simulation.duration / scene.simulation.dt)
    checks = scene_checks(sim)
    checks.add(sim.q, [(v, f) for _, v, f in sim.obstacles()])
    kinetic = [0.5 * float(sim.v.reshape(-1) @ (sim.model.mass @ sim.v.reshape(-1)))]
    newton, cpu, wall = 0, 0.0, 0.0
    for _ in range(n):
        c0, t0 = time.process_time(), time.perf_counter()
        info = sim.step()
        cpu += time.process_time() - c0
        wall += time.perf_counter() - t0
        newton += info.newton_iterations
        kinetic.append(info.kinetic)
        checks.add(sim.q, [(v, f) for _, v, f in sim.obstacles()])
    # "at rest" by kinetic energy can hide creep under smoothed static friction (vertices
    # sliding at about eps_v): the fastest vertex at the end shows it
    speeds = np.linalg.norm(sim.v.reshape(-1, 3), axis=1)
    moving = [(b.name or f"body {i}", float(speeds[rows].max()))
              for i, (b, rows) in enumerate(zip(scene.bodies, sim.assembled.body_vertices,
                                                strict=True))
              if speeds[rows].max() > MOVING]
    return checks, np.asarray(kinetic), {"steps": n, "cpu": cpu, "wall": wall,
                                         "newton": newton, "tets": sim.model.n_tets,
                                         "end_speed": float(speeds.max()), "moving": moving}


def report(name: str, checks: StateChecks, kinetic: np.ndarray, figures: dict, rest: float,
           must_rest: bool) -> bool:
    """Print the scene's line; True when its checks pass."""
    k = rest_step(kinetic, rest)
    rested = k is not None
    ok = checks.ok and (rested or not must_rest)
    n = figures["steps"]
    plane = f", closest to a plane {checks.min_plane_gap * 1e3:.4f} mm" if checks.planes else ""
    box = (f", closest to the box {checks.min_box_clearance * 1e3:.3f} mm "
           f"({len(checks.outside_box)} states outside)" if checks.box is not None else "")
    rest_text = (f"at rest (below {rest:g} of the peak) from step {k}" if rested else
                 f"not at rest ({kinetic[-1] / kinetic.max():.1e} of the peak at the end)")
    window = None if rested else last_rest(kinetic, rest)
    if window is not None:
        rest_text += f", after resting over steps {window[0]}-{window[1]}"
    moving = figures.get("moving", [])
    if moving and not rested:
        rest_text += ", moving at the end: " + ", ".join(
            f"{name} {speed * 1e3:.1f} mm/s" for name, speed in moving[:6])
    print(f"{name}: {figures['tets']:,} tets, {n} steps, {n / max(figures['wall'], 1e-9):.2f} "
          f"steps/s ({n / max(figures['cpu'], 1e-9):.2f} CPU), "
          f"{figures['newton'] / n:.2f} Newton/step; {checks.states} states checked: "
          f"{len(checks.intersecting)} intersect "
          f"{checks.intersecting[:5]}, {len(checks.behind_plane)} behind a plane{plane}{box}; "
          f"kinetic energy peak {kinetic.max():.3e} J at step {int(kinetic.argmax())}, "
          f"{rest_text}{'' if must_rest else ' (not required)'}, fastest vertex at the end "
          f"{figures['end_speed'] * 1e3:.2f} mm/s: {'OK' if ok else 'FAILED'}")
    return ok


def main(argv: list[str] | None = None) -> int:
    from fem3d.app.cli import parse_assignments
    from fem3d.scene import apply_overrides, load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="*", help="gallery scene names (default: every contact_*)")
    ap.add_argument("--steps", type=int, default=None, help="default: each scene's duration")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--rest", type=float, default=1e-6)
    args = ap.parse_args(argv)
    names = args.scenes or sorted(p.stem for p in SCENES.glob("contact_*.toml"))
    overrides = dict(parse_assignments(args.set))
    ok = True
    for name in names:
        scene = apply_overrides(load_scene(name), overrides)
        checks, kinetic, figures = run_and_check(scene, args.steps)
        must_rest = name in COMES_TO_REST and args.steps is None
        ok &= report(name, checks, kinetic, figures, args.rest, must_rest)
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
