"""The restructured code takes bit for bit the steps the code before it took.

``tests/data/trajectories_before_restructure.npz`` was recorded by
``tests/record_trajectories.py`` at commit 6cbcdd9, before the subpackages, objective terms and
the small integrator (issue 19): the SHA-256 of q and v after every step of every gallery
scene, the classic bunny and armadillo, and the Newton variants (``reuse``, the PSD Hessian,
AMG, the NumPy kernels). Any change of round-off fails here, naming the first step that moved.
``tests/data/checkpoints_before_restructure/`` holds two checkpoints written by that code; they
resume under the new code to the recorded final state of the uninterrupted run.

The two surface scenes (``bunny_surface``, ``armadillo_surface``) depend on fTetWild, whose
mesh differs from run to run of the same input: their first recording held the meshes of that
machine's cache, which a fresh machine cannot reproduce. They were re-recorded on 2026-12-02 by
the same code (6cbcdd9, in a worktree of its own) with the meshes fixed in
``tests/data/tetwild/`` (``record_trajectories.fixed_tetwild_meshes``), so they still compare
the new code against the code before the restructuring.

``contact_stack`` and ``contact_twisted_bar`` were re-recorded on 2026-12-02 by the contact
candidates change (issue 21): the leaner contact pattern changes CHOLMOD's fill-reducing
ordering, so their round-off (the twisted bar moves 5e-17 m; the chaotic stack drifts no more
than the old code does from itself with gravity one ulp off: ``python -m bench.contact_oldnew``
prints both side by side). Every other case still holds the code before the restructuring.

Scenes that changed since keep the settings they were recorded with (``record_trajectories``'s
overrides): ``contact_bunny_drop`` without the self-contact and damping it gained, and
the contact scenes without the Newton start and substeps the gallery's scene files set since
(``contact.newton_start = "clamped"``, ``contact.max_substeps = 1``, the spec's defaults).
The four cases that project an indefinite ``dP/dF`` (Newton's ``psd`` Hessian, stiffness
damping: ``arma_psd``, ``cantilever``, ``cantilever_amg``, ``armadillo_surface``) keep the
cyclic Jacobi projection they were recorded with (``simulation.psd_projection = "jacobi"``;
QL replaced it as the default at stop 31).

The last bits of some cases depend on the CPU (the BLAS and NumPy kernels a machine's
instruction set selects: dot products in CG and in the energies): on an AMD EPYC with
AVX-512 (Zen 4), 12 of the 21 cases part from the recording at their first step by 3e-17 to
4e-13 m, the resumed drop checkpoint too, while the code that does so is the one CI had just
proven bit for bit equal to the recording on its own machine (98f2bc5, stop 28).
``tests/data/trajectories_amd_epyc_avx512.npz`` holds those 12 cases as that code steps them
on such a CPU (2026-12-02, ``python tests/record_trajectories.py OUT`` and the checkpoint's
resume, keeping the cases that differ): a case passes when it matches every step of one
recording of it, the original or that CPU's. On an AMD EPYC of the next generation (Zen 5,
CPU family 26: the compiler's ``-march=native`` tuning and the BLAS kernels change again) 8
cases part from both; ``tests/data/trajectories_amd_zen5.npz`` holds them as stepped there on
2026-12-03 by 380e6d1 (the code CI had just proven equal to the recordings, stop 30).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from record_trajectories import CASES, digest, run_case  # tests/ is on sys.path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RECORDING = HERE / "data" / "trajectories_before_restructure.npz"
#: the cases whose round-off differs on that CPU, as the same code steps them there
RECORDING_AVX512 = HERE / "data" / "trajectories_amd_epyc_avx512.npz"
RECORDING_ZEN5 = HERE / "data" / "trajectories_amd_zen5.npz"
CHECKPOINTS = HERE / "data" / "checkpoints_before_restructure"
RECORDED_ROOT = "/work/main"  # the checkout the checkpoints were written in


@pytest.fixture(scope="module")
def recording():
    return np.load(RECORDING)


@pytest.fixture(scope="module")
def recordings(recording):
    """The original recording first, then the other CPUs'."""
    return [recording, np.load(RECORDING_AVX512), np.load(RECORDING_ZEN5)]


@pytest.mark.parametrize("name, scene_name, steps, overrides", CASES, ids=[c[0] for c in CASES])
def test_trajectory_is_bit_identical_to_the_recording(recordings, name, scene_name, steps,
                                                      overrides):
    digests, q, v = run_case(scene_name, steps, overrides)
    parted = []
    for rec in recordings:
        if f"{name}__digests" not in rec.files:
            continue
        want = rec[f"{name}__digests"]
        assert len(digests) == len(want) == steps
        moved = [i for i, (a, b) in enumerate(zip(digests, want, strict=True)) if a != b]
        if not moved:
            assert np.array_equal(q, rec[f"{name}__q"])
            assert np.array_equal(v, rec[f"{name}__v"])
            return
        parted.append(f"step {moved[0] + 1} (final |dq| "
                      f"{float(np.abs(q - rec[f'{name}__q']).max()):.3g})")
    pytest.fail(f"{name}: parts from every recording of it, first at " + ", ".join(parted))


def _relocated_checkpoint(src: Path, dst: Path) -> None:
    """``src`` with the recording checkout's absolute paths pointed at this checkout."""
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = bytes(arrays["__fem3d_metadata__"]).decode()
    meta = meta.replace(json.dumps(RECORDED_ROOT)[1:-1], json.dumps(str(ROOT))[1:-1])
    arrays["__fem3d_metadata__"] = np.frombuffer(meta.encode(), dtype=np.uint8)
    with open(dst, "wb") as f:
        np.savez(f, **arrays)


@pytest.mark.parametrize("file, case, final_step", [
    ("arma_step50.npz", "arma", 100),
    ("contact_bunny_drop_reuse_step40.npz", "contact_bunny_drop_reuse", 80),
])
def test_checkpoint_written_before_resumes_to_the_recorded_state(tmp_path, recordings, file,
                                                                 case, final_step):
    run = tmp_path / "run"
    run.mkdir()
    _relocated_checkpoint(CHECKPOINTS / file, run / "checkpoint.npz")
    proc = subprocess.run([sys.executable, "-m", "fem3d", "resume", str(run), "--steps",
                           str(final_step), "--quiet", "--no-preview"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"-> {final_step} ->" in proc.stderr + proc.stdout
    with np.load(run / "checkpoint.npz", allow_pickle=False) as z:
        q, v = z["state_q"], z["state_v"]
    original, *others = recordings
    # on another CPU the resumed steps are that CPU's (from the original's step 40 or 50)
    want = {str(original[f"{case}__digests"][final_step - 1])}
    want |= {str(r[f"{case}__resumed_digest"]) for r in others
             if f"{case}__resumed_digest" in r.files}
    assert digest(q) + digest(v) in want
    shutil.rmtree(run)
