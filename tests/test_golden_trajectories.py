"""Golden trajectories: the results of a dozen scenes, bit for bit, on 1, 2 and 3 threads.

Every integrator with and without FEPR, contact with the ground, kinematic pins with damping, two bodies, and two
real meshes (the quality guard's search on bunny2). Each run is hashed (SHA-256 over the final positions and
velocities and every history column but the timings) and compared with ``golden_trajectories.json``. A change
that moves any bit of any of these results fails here: refactors must not, and a change that means to alter
results regenerates the file on purpose (``FEPR_GOLDEN_UPDATE=1 python -m pytest tests/test_golden_trajectories.py``)
and says why in its commit.

The hashes hold on the platform CI runs on (x86-64 Linux, the same libm); the thread counts must agree with each
other everywhere.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any, Callable, Dict

import numpy as np
import pytest

import fepr
from conftest import shared_meshes_dir
from fepr.cli.demo import DEMO_SCENES
from fepr.scene import scene_from_dict

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

HERE = Path(__file__).resolve().parent
EXAMPLES = HERE.parent / "examples"
GOLDEN = HERE / "golden_trajectories.json"
THREADS = (1, 2, 3)
# The guard's unresolved-energy warnings are expected on the real meshes.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")
# Wall-clock columns: the only ones allowed to differ between runs.
TIMING_COLUMNS = {"base_ms", "proj_ms"}


def _demo(name: str, steps: int, integrator: str | None = None, projection: bool = True) -> Callable[[int], Any]:
    def build(threads: int):
        d = copy.deepcopy(DEMO_SCENES[name])
        if integrator is not None:
            d["integrator"]["name"] = integrator
        d["projection"]["enabled"] = projection
        d["run"] = {"steps": steps, "threads": threads}
        return scene_from_dict(d, ".", source=name), steps

    return build


def _example(name: str, steps: int) -> Callable[[int], Any]:
    def build(threads: int):
        with open(EXAMPLES / f"{name}.toml", "rb") as f:
            d = tomllib.load(f)
        d["run"] = {"steps": steps, "threads": threads}
        return scene_from_dict(d, EXAMPLES, source=name), steps

    return build


def _stretched_mesh(
    file: str, integrator: str, steps: int, dt: float = 1 / 60, projection: bool = True
) -> Callable[[int], Any]:
    """A shared real mesh fit to 0.3 m, Stable Neo-Hookean 1e5 Pa / 0.4, 1000 kg/m^3, released from a 10% stretch."""

    def build(threads: int):
        meshes = shared_meshes_dir()
        if meshes is None:
            pytest.skip("the shared test meshes are not present")
        mesh = fepr.load_mesh(meshes / file, fit=0.3, center="bbox")
        sim = fepr.Simulation(
            mesh,
            material=fepr.StableNeoHookean(1e5, 0.4),
            density=1000.0,
            integrator=integrator,
            dt=dt,
            projection=projection,
            threads=threads,
        )
        sim.positions = 1.1 * sim.rest_positions
        return sim, steps

    return build


SCENES: Dict[str, Callable[[int], Any]] = {
    "seed_demo3_stretch/symplectic_euler+fepr": _demo("seed_demo3_stretch", 60),
    "spinning_l_gravity/symplectic_euler": _demo("spinning_l_gravity", 40, projection=False),
    "implicit_ell/implicit_euler+fepr": _demo("implicit_ell", 20),
    "implicit_ell/implicit_euler": _demo("implicit_ell", 20, projection=False),
    "implicit_ell/projective_dynamics+fepr": _demo("implicit_ell", 30, integrator="projective_dynamics"),
    "implicit_ell/projective_dynamics": _demo("implicit_ell", 30, integrator="projective_dynamics", projection=False),
    "implicit_ell/xpbd+fepr": _demo("implicit_ell", 20, integrator="xpbd"),
    "implicit_ell/xpbd": _demo("implicit_ell", 20, integrator="xpbd", projection=False),
    "implicit_cantilever/projective_dynamics+fepr": _demo("implicit_cantilever", 30, integrator="projective_dynamics"),
    "drop_box/contact+fepr": _example("drop_box", 300),
    "hanging_bar/pins+damping+fepr": _example("hanging_bar", 40),
    "two_bodies/contact+wind+fepr": _example("two_bodies", 200),
    "armadillo/implicit_euler+fepr": _stretched_mesh("Armadillo_Tetra_4406.vtu", "implicit_euler", 4),
    "bunny2/projective_dynamics+fepr (guard)": _stretched_mesh("seed/bunny2.1.node", "projective_dynamics", 8),
}


def _run(build: Callable[[int], Any], threads: int):
    obj, steps = build(threads)
    if hasattr(obj, "build_bodies"):
        obj = obj.build_multibody() if obj.is_multibody else obj.build()
    obj.step(steps)
    return obj


def _digest(sim) -> str:
    """SHA-256 over the final state and every history column but the timings, in a fixed order."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(sim.positions, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(sim.velocities, dtype=np.float64).tobytes())
    histories = [sim.history] + [b.history for b in getattr(sim, "bodies", [])]
    for hist in histories:
        for name in sorted(hist.columns):
            if name in TIMING_COLUMNS:
                continue
            h.update(name.encode())
            h.update(np.ascontiguousarray(hist[name], dtype=np.float64).tobytes())
    return h.hexdigest()


def _golden() -> Dict[str, str]:
    return json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}


@pytest.mark.parametrize("name", list(SCENES))
def test_golden_trajectory_is_bit_identical_on_every_thread_count(name):
    digests = {t: _digest(_run(SCENES[name], t)) for t in THREADS}
    assert len(set(digests.values())) == 1, f"{name}: the thread counts disagree: {digests}"
    digest = digests[THREADS[0]]
    if os.environ.get("FEPR_GOLDEN_UPDATE") == "1":
        golden = _golden()
        golden[name] = digest
        GOLDEN.write_text(json.dumps(dict(sorted(golden.items())), indent=2) + "\n")
        return
    golden = _golden()
    assert name in golden, f"no golden hash for {name!r}: record it with FEPR_GOLDEN_UPDATE=1"
    assert digest == golden[name], f"{name}: the trajectory changed (hash {digest}, golden {golden[name]})"
