"""NVIDIA Newton's VBD solver (``pip install newton warp-lang``, Warp on the CPU) on fepr's pile scene.

Measures what a peer simulator does on ``examples/pile.toml``: eight soft bodies (four balls, four boxes,
20,520 tets in all) dropped into a bin (the floor z = 0 and four thin box walls), dt = 1/60. Newton runs
them with ``SolverVBD`` (vertex block descent, Neo-Hookean tets, 10 iterations a step, one step per frame
as fepr takes), its collision pipeline for the particle-versus-floor/wall contacts and VBD's own
vertex-triangle / edge-edge self-contact for body-versus-body contact. It prints

- ms per step over 120 steps (2 s of scene time), after a warm-up run that compiles Warp's kernels;
- from Newton's final particle positions: the lowest z of any vertex (did anything go through the floor),
  the number of inverted tets, and, for every ordered pair of bodies, how many vertices of one lie inside
  the other's tets (interpenetration).

fepr is not needed here: the pile's meshes, masses and positions come from an .npz exported with fepr's
own Python (keys ``x{k}``, ``t{k}``, ``m{k}`` for body k and ``n_bodies``), e.g.::

    from fepr.scene import load_scene
    mb = load_scene("examples/pile.toml").build_multibody()
    np.savez(path, n_bodies=len(mb.bodies), **{f"{n}{k}": a for k, b in enumerate(mb.bodies)
             for n, a in (("x", b.positions), ("t", b.tets), ("m", b.masses))})

Run by hand (it is not part of fepr's tests), in an environment with newton, warp-lang, numpy::

    python benchmarks/peers/peer_newton_pile.py /tmp/peerpile/pile.npz [--steps 120] [--iterations 10]

Material, density and contact values below are those of ``examples/pile.toml``; restitution (0.3 there) has
no counterpart in VBD's penalty contact, which is damped by ``kd`` instead.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

# examples/pile.toml: every body and obstacle uses the same values.
YOUNGS_MODULUS = 1e5  # Pa
POISSON_RATIO = 0.4
DENSITY = 1000.0  # kg/m^3
FRICTION = 0.4
GRAVITY = (0.0, 0.0, -9.81)
DT = 1.0 / 60.0
WALLS = [  # (center, half extents), the bin's four walls
    ((-0.52, 0.0, 0.3), (0.02, 0.54, 0.3)),
    ((0.52, 0.0, 0.3), (0.02, 0.54, 0.3)),
    ((0.0, -0.52, 0.3), (0.54, 0.02, 0.3)),
    ((0.0, 0.52, 0.3), (0.54, 0.02, 0.3)),
]

# Newton's contact settings (no counterpart in the TOML). The penalty stiffness is far above a vertex's
# weight over a millimetre (~0.2 N / 1e-3 m), so resting penetration stays well under a millimetre; the
# contact distances are a small fraction of the ~37 mm edge length, since VBD's default self-contact margin
# (0.2 m) is as large as the bodies themselves.
CONTACT_KE = 1e5  # N/m
CONTACT_KD = 10.0  # N s/m, Newton's Model default
PARTICLE_RADIUS = 5e-3  # m, particle-versus-shape contact distance
SELF_CONTACT_MARGIN = 5e-3  # m, vertex-triangle / edge-edge interaction distance
SELF_CONTACT_GAP = 5e-3  # m, extra detection slack


def lame(E: float, nu: float) -> tuple[float, float]:
    """(mu, lambda) of Young's modulus and Poisson's ratio."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def load_bodies(path: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    data = np.load(path)
    return [
        (np.asarray(data[f"x{k}"], float), np.asarray(data[f"t{k}"], np.int64), np.asarray(data[f"m{k}"], float))
        for k in range(int(data["n_bodies"]))
    ]


def build_model(bodies):
    import newton
    import warp as wp

    mu, lam = lame(YOUNGS_MODULUS, POISSON_RATIO)
    builder = newton.ModelBuilder(gravity=GRAVITY)
    cfg = newton.ModelBuilder.ShapeConfig()
    # The solver averages the shape's ke/kd/mu with the model's soft_contact_*; equal values keep the
    # TOML's friction exact.
    cfg.ke, cfg.kd, cfg.mu = CONTACT_KE, CONTACT_KD, FRICTION
    builder.add_ground_plane(cfg=cfg)
    for center, half in WALLS:
        builder.add_shape_box(
            -1, xform=wp.transform(wp.vec3(*center), wp.quat_identity()), hx=half[0], hy=half[1], hz=half[2], cfg=cfg
        )
    offsets = [0]
    for x, tets, _ in bodies:
        builder.add_soft_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=[wp.vec3(*p) for p in x],
            indices=tets.astype(np.int32).ravel().tolist(),
            density=DENSITY,
            k_mu=mu,
            k_lambda=lam,
            k_damp=0.0,  # fepr's pile has no material damping
            particle_radius=PARTICLE_RADIUS,
        )
        offsets.append(offsets[-1] + len(x))
    builder.color()  # VBD needs a vertex colouring: Gauss-Seidel, parallel within a colour
    model = builder.finalize(device="cpu")
    model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = CONTACT_KE, CONTACT_KD, FRICTION
    return model, offsets


def make_sim(model, iterations: int, self_contact: bool):
    """A fresh solver, collision pipeline and initial states (the kernels, once compiled, are reused)."""
    import newton

    solver = newton.solvers.SolverVBD(
        model,
        iterations=iterations,
        particle_enable_self_contact=self_contact,  # the only body-versus-body contact VBD has for particles
        particle_self_contact_margin=SELF_CONTACT_MARGIN,
        particle_self_contact_gap=SELF_CONTACT_GAP,
    )
    pipeline = newton.CollisionPipeline(model)
    return solver, pipeline, pipeline.contacts(), model.state(), model.state(), model.control()


def run(model, iterations: int, steps: int, self_contact: bool) -> tuple[float, float, np.ndarray]:
    """Seconds per step over `steps` steps from the initial state, the part of it spent in the collision
    pipeline (floor and walls), and the final particle positions."""
    import warp as wp

    solver, pipeline, contacts, s0, s1, control = make_sim(model, iterations, self_contact)
    wp.synchronize()
    t_collide = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        s0.clear_forces()
        tc = time.perf_counter()
        pipeline.collide(s0, contacts)
        wp.synchronize()
        t_collide += time.perf_counter() - tc
        solver.step(s0, s1, control, contacts, DT)
        s0, s1 = s1, s0
    wp.synchronize()
    return (time.perf_counter() - t0) / steps, t_collide / steps, s0.particle_q.numpy().astype(float)


def points_in_tets(points: np.ndarray, x: np.ndarray, tets: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Which points lie strictly inside any of the tets (the body's actual tets, so non-convex bodies are
    right). Tets are bucketed on a grid of about one tet's size, so each point is tested only against the
    tets whose boxes cover its cell."""
    inside = np.zeros(len(points), bool)
    lo_all, hi_all = x[tets].min(axis=(0, 1)), x[tets].max(axis=(0, 1))
    cand = np.nonzero(np.all((points >= lo_all) & (points <= hi_all), axis=1))[0]
    if len(cand) == 0:
        return inside
    tlo, thi = x[tets].min(axis=1), x[tets].max(axis=1)
    h = float(np.median(thi - tlo))
    ilo = np.floor((tlo - lo_all) / h).astype(np.int64)
    ihi = np.floor((thi - lo_all) / h).astype(np.int64)
    dims = np.floor((hi_all - lo_all) / h).astype(np.int64) + 1

    # (cell, tet) pairs for every cell a tet's box covers, sorted by cell.
    cells, owners = [], []
    for t in range(len(tets)):
        gx, gy, gz = np.meshgrid(*(np.arange(ilo[t, a], ihi[t, a] + 1) for a in range(3)), indexing="ij")
        c = (gx.ravel() * dims[1] + gy.ravel()) * dims[2] + gz.ravel()
        cells.append(c)
        owners.append(np.full(len(c), t))
    cells, owners = np.concatenate(cells), np.concatenate(owners)
    order = np.argsort(cells, kind="stable")
    cells, owners = cells[order], owners[order]

    p = points[cand]
    ip = np.minimum(np.floor((p - lo_all) / h).astype(np.int64), dims - 1)
    pc = (ip[:, 0] * dims[1] + ip[:, 1]) * dims[2] + ip[:, 2]
    start, stop = np.searchsorted(cells, pc, "left"), np.searchsorted(cells, pc, "right")
    count = stop - start
    qi = np.repeat(np.arange(len(p)), count)
    ti = owners[np.repeat(start, count) + (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count))]

    # Barycentric coordinates of each (point, tet) candidate.
    a = x[tets[ti, 0]]
    m = np.stack([x[tets[ti, 1]] - a, x[tets[ti, 2]] - a, x[tets[ti, 3]] - a], axis=2)
    b = np.linalg.solve(m, (p[qi] - a)[..., None])[..., 0]
    hit = (b.min(axis=1) > tol) & (b.sum(axis=1) < 1.0 - tol)
    inside[cand[np.unique(qi[hit])]] = True
    return inside


def in_walls(points: np.ndarray) -> int:
    """How many points lie inside a wall box."""
    n = np.zeros(len(points), bool)
    for center, half in WALLS:
        n |= np.all(np.abs(points - np.asarray(center)) < np.asarray(half), axis=1)
    return int(n.sum())


def inverted_tets(x: np.ndarray, tets: np.ndarray) -> int:
    a = x[tets[:, 0]]
    vol = np.einsum("ij,ij->i", np.cross(x[tets[:, 1]] - a, x[tets[:, 2]] - a), x[tets[:, 3]] - a)
    return int(np.sum(vol <= 0.0))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("npz", help="the pile exported from fepr (see the module docstring)")
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--iterations", type=int, default=10, help="VBD iterations per step")
    parser.add_argument("--warmup-steps", type=int, default=2)
    parser.add_argument("--no-self-contact", action="store_true", help="turn VBD's body-body contact off")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    import newton

    wp.set_device("cpu")
    bodies = load_bodies(args.npz)
    model, offsets = build_model(bodies)
    print(f"newton {newton.__version__}, warp {wp.__version__}, device {wp.get_device()}")
    print(
        f"{len(bodies)} bodies, {model.particle_count} vertices, {model.tet_count} tets, "
        f"{model.tri_count} surface triangles, {model.edge_count} edges; "
        f"mass {float(np.sum(model.particle_mass.numpy())):.3f} kg (fepr {sum(m.sum() for _, _, m in bodies):.3f})"
    )

    t0 = time.perf_counter()
    self_contact = not args.no_self_contact
    run(model, args.iterations, args.warmup_steps, self_contact)  # compiles the kernels; its states are thrown away
    print(f"warm-up ({args.warmup_steps} steps, kernel compilation): {time.perf_counter() - t0:.1f} s")

    per_step, collide, q = run(model, args.iterations, args.steps, self_contact)
    print(
        f"SolverVBD, {args.iterations} iterations, dt = 1/60, self-contact {'on' if self_contact else 'off'}: "
        f"{1e3 * per_step:.1f} ms/step over {args.steps} steps ({1e3 * collide:.1f} ms of it in the collision pipeline)"
    )

    finite = bool(np.all(np.isfinite(q)))
    print(f"finite: {finite}; lowest z: {q[:, 2].min():.5f} m; vertices inside a wall: {in_walls(q)}")
    xs = [q[offsets[k] : offsets[k + 1]] for k in range(len(bodies))]
    for k, (x, (_, tets, _)) in enumerate(zip(xs, bodies)):
        print(
            f"body {k}: z from {x[:, 2].min():+.5f} to {x[:, 2].max():.4f} m (mean {x[:, 2].mean():.4f}), "
            f"inverted tets {inverted_tets(x, tets)}"
        )
    if not finite:
        return 1
    total = 0
    for i in range(len(bodies)):
        for j in range(len(bodies)):
            if i != j:
                n = int(points_in_tets(xs[i], xs[j], bodies[j][1]).sum())
                total += n
                if n:
                    print(f"vertices of body {i} inside body {j}: {n}")
    print(f"interpenetration: {total} (vertex, other body) pairs with the vertex inside the other body's tets")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
