"""The pile's contact detection against IPC Toolkit's (``pip install ipctk``), on the same state.

Runs ``examples/pile.toml`` (8 bodies, 20,520 tets, Projective Dynamics at dt = 1/60 with FEPR) for ``--steps``
steps, then times at that state, alternating, ``--rounds`` times each, best of the rounds:

- fepr: one detection pass between the bodies (`fepr._core.bench_body_detection`: each surface follows its body,
  pairs with overlapping boxes, each surface vertex inside the other's box queried against its surface);
- ipctk: `NormalCollisions.build` on the bodies' surfaces merged into one collision mesh (its broad phase, then
  every vertex-face, edge-edge, edge-vertex and vertex-vertex pair within `dhat`), with `--dhat` (m, default
  1e-3) and its default broad phase.

They do not compute the same thing: IPC lists every primitive pair closer than `dhat` (its barrier needs them,
edge-edge included), fepr only finds surface vertices inside another body. IPC Toolkit has no simulator; the
pile's step itself cannot be run by it.

    python benchmarks/peers/peer_ipc_pile.py [--steps 30] [--rounds 5] [--dhat 0.001] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np


def surfaces(system):
    """All bodies' boundary triangles in the concatenated vertex numbering, (f, 3) int32."""
    tris = []
    for k, body in enumerate(system.bodies):
        t = np.asarray(body.tets)
        f = np.concatenate([t[:, [1, 2, 3]], t[:, [0, 3, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 1]]])
        _, first, count = np.unique(np.sort(f, axis=1), axis=0, return_index=True, return_counts=True)
        tris.append(f[first[count == 1]] + int(system.offsets[k]))
    return np.concatenate(tris).astype(np.int32)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--dhat", type=float, default=1e-3, help="IPC activation distance, m")
    parser.add_argument("--json", help="write the numbers as JSON")
    args = parser.parse_args()

    import ipctk

    from fepr import _core
    from fepr.cli.bench_contact import pile_scene
    from fepr.scene import scene_from_dict

    system = scene_from_dict(pile_scene(), ".").build_multibody()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        system.step(args.steps)
    faces = surfaces(system)
    x = np.asfortranarray(system.positions)
    mesh = ipctk.CollisionMesh.build_from_full_mesh(
        np.asfortranarray(system.rest_positions), np.asfortranarray(ipctk.edges(faces)), np.asfortranarray(faces)
    )
    xs = np.asfortranarray(mesh.vertices(x))
    dhat = args.dhat
    fepr_s, ipc_s, found = [], [], 0
    for _ in range(args.rounds):
        fepr_s.append(_core.bench_body_detection([b._sim for b in system.bodies], 3))
        collisions = ipctk.NormalCollisions()
        t0 = time.perf_counter()
        collisions.build(mesh, xs, dhat)
        ipc_s.append(time.perf_counter() - t0)
        found = len(collisions)
    out = {
        "steps": args.steps,
        "surface_vertices": int(mesh.num_vertices),
        "surface_faces": int(len(faces)),
        "fepr_detection_ms": 1e3 * min(fepr_s),
        "ipctk_build_ms": 1e3 * min(ipc_s),
        "ipctk_collisions_within_dhat": int(found),
        "dhat_m": dhat,
    }
    print(
        f"pile after {args.steps} steps, {out['surface_vertices']} surface vertices, {out['surface_faces']} faces: "
        f"fepr detection {out['fepr_detection_ms']:.2f} ms, "
        f"ipctk NormalCollisions.build {out['ipctk_build_ms']:.2f} ms ({found} pairs within dhat = {dhat} m)"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
