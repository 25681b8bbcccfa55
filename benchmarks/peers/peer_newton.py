"""NVIDIA Newton (``pip install newton``, Warp on the CPU): its semi-implicit (symplectic Euler) solver on a
Neo-Hookean tet mesh, timed per step. Set-up as the issue prescribes: a particle radius far below the edge
length, the brute-force triangle contact off (with it on, a step is hundreds of times slower) and no
particle-particle contact grid; no gravity, no damping, no ground."""

from __future__ import annotations

import time

import numpy as np


def time_step(rest, tets, mu, lam, density, x0, dt, budget_s=1.0, min_steps=3, solver="semi_implicit"):
    """Seconds per step of Newton's solver on the CPU, after a warm-up step (which compiles the kernels)."""
    import warp as wp

    wp.config.quiet = True
    import newton

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    edge = float(np.min(np.linalg.norm(rest[tets[:, 1]] - rest[tets[:, 0]], axis=1)))
    builder.add_soft_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*p) for p in x0],
        indices=np.asarray(tets, dtype=np.int32).ravel().tolist(),
        density=density,
        k_mu=mu,
        k_lambda=lam,
        k_damp=0.0,
        particle_radius=1e-3 * edge,
    )
    if solver == "vbd":
        builder.color()  # VBD's vertex colouring (Gauss-Seidel in parallel per colour)
    with wp.ScopedDevice("cpu"):
        model = builder.finalize(device="cpu")
        # No particle-particle contact (its hash grid is rebuilt every step otherwise).
        model.particle_grid = None
        if solver == "semi_implicit":
            s = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
        elif solver == "vbd":
            s = newton.solvers.SolverVBD(model, iterations=10)
        else:
            raise ValueError(solver)
        state_0, state_1 = model.state(), model.state()
        control = model.control()
        s.step(state_0, state_1, control, None, dt)  # compiles the kernels
        state_0, state_1 = state_1, state_0
        wp.synchronize()
        n, t0 = 0, time.perf_counter()
        while n < min_steps or time.perf_counter() - t0 < budget_s:
            s.step(state_0, state_1, control, None, dt)
            state_0, state_1 = state_1, state_0
            n += 1
        wp.synchronize()
        per_step = (time.perf_counter() - t0) / n
        ok = bool(np.all(np.isfinite(state_0.particle_q.numpy())))
    return per_step, ok
