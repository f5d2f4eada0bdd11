"""Bit for bit within one machine: the same run twice, in this process and in others, and a run
interrupted by a checkpoint and ``fem3d resume``d (issue 39; docs/testing.md).

Every comparison is between runs made during the test, never against a committed file: bits
are a property of one machine (``tests/simulation/test_trajectories.py`` holds what any machine must
reproduce). The cases: a classic scene (``arma``: direct Newton, scripted pulls), the Newton
solvers that keep state between steps (``arma_reuse``: a factorization as CG's preconditioner;
``cantilever_amg``: AMG's hierarchy) and a contact case (``contact_bunny_drop_reuse``: barrier
stiffness, lagged friction and CG together; chaotic, so a moved bit shows within a few steps).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.record_trajectories import (
    CASE,
    digest,
    fem3d_in_a_new_process,
    run_case,
    trajectory,
)

#: case -> the step where the interrupted run stops and checkpoints (not a round number; the
#: drop's is after the landing at step 22, with contacts, friction and CG state to carry)
STOP = {"arma": 37, "arma_reuse": 50, "cantilever_amg": 9, "contact_bunny_drop_reuse": 30}


@pytest.mark.parametrize("name", STOP)
def test_the_same_run_twice_in_one_process_is_bit_identical(name):
    _, scene_name, steps, overrides = CASE[name]
    again = run_case(scene_name, steps, overrides)
    first = trajectory(name).digests
    moved = [k + 1 for k, (a, b) in enumerate(zip(first, again.digests, strict=True)) if a != b]
    assert not moved, f"{name}: the second run parts from the first at step {moved[0]}"


def _run_args(name: str, out, steps: int) -> list[str]:
    """``fem3d run`` of case ``name`` to ``steps``, checkpointed there."""
    _, scene_name, _, overrides = CASE[name]
    overrides = dict(overrides)
    args = ["run", scene_name, "--steps", str(steps), "--checkpoint-every", str(steps),
            "--frame-every", str(steps), "--out", str(out), "--no-preview", "--quiet"]
    if "_backend" in overrides:
        args += ["--kernels", overrides.pop("_backend")]
    for key, value in overrides.items():  # JSON's strings, booleans and numbers are TOML's
        args += ["--set", f"{key}={json.dumps(value)}"]
    return args


def _checkpoint_digest(out) -> str:
    with np.load(out / "checkpoint.npz", allow_pickle=False) as z:
        return digest(z["state_q"]) + digest(z["state_v"])


@pytest.fixture(scope="module")
def interrupted_runs(tmp_path_factory) -> dict[str, tuple[str, str]]:
    """Each case run by ``fem3d run`` to its stop in one new process, then ``fem3d resume``d
    to the end in another: the checkpoint's q, v digests after each."""
    root = tmp_path_factory.mktemp("determinism")
    fem3d_in_a_new_process([_run_args(name, root / name, stop) for name, stop in STOP.items()],
                           root)
    stopped = {name: _checkpoint_digest(root / name) for name in STOP}
    fem3d_in_a_new_process([["resume", str(root / name), "--steps", str(CASE[name][2]),
                             "--no-preview", "--quiet"] for name in STOP], root)
    return {name: (stopped[name], _checkpoint_digest(root / name)) for name in STOP}


@pytest.mark.parametrize("name", STOP)
def test_another_process_and_its_resume_take_the_same_steps(interrupted_runs, name):
    """``fem3d run`` in another process reaches this process's state at the stop, bit for bit,
    and ``fem3d resume`` from its checkpoint (a third process) the uninterrupted run's end."""
    stopped, end = interrupted_runs[name]
    digests = trajectory(name).digests
    assert stopped == digests[STOP[name] - 1], f"{name}: another process parts by the stop"
    assert end == digests[-1], f"{name}: the resumed run parts from the uninterrupted one"
