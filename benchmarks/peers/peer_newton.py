"""NVIDIA Newton (``pip install newton``, Warp on the CPU): its semi-implicit (symplectic Euler), VBD and XPBD
solvers on a Neo-Hookean tet mesh, timed per step.

Newton's ``add_soft_mesh(vertices=...)`` takes the **rest shape**: ``add_tetrahedron`` builds each tet's rest
pose (``tet_poses``, the inverse rest edge matrix), its volume and the lumped masses from the particle positions
at build time. So the model is built on ``rest`` and the deformed start ``x0`` is written into the initial
state's ``particle_q`` afterwards (before round 15 the stretched positions were passed as ``vertices=``, so
Newton simulated a body at rest and the stretch exerted no force).

Set-up for the elastic-only scenes: a particle radius far below the edge length, the brute-force triangle
contact off (with it on, a step is hundreds of times slower) and no particle-particle contact grid; no damping.
With ``ground=True``: gravity along -z and Newton's ground plane z = 0, particle-versus-shape contact from its
collision pipeline each step (the step's time includes it), penalty stiffness ``CONTACT_KE``."""

from __future__ import annotations

import time

import numpy as np

CONTACT_KE = 1e5  # N/m, as peer_newton_pile.py (Newton's default 1e3 lets a 100 kg body sink centimetres)
CONTACT_KD = 10.0  # N s/m, Newton's default
GROUND_PARTICLE_RADIUS = 5e-3  # m, the particle-versus-ground contact distance


def build(rest, tets, mu, lam, density, *, solver="semi_implicit", gravity=(0.0, 0.0, 0.0), ground=None):
    """Newton's model on the rest shape. ``ground``: None, or the ground's Coulomb friction coefficient."""
    import warp as wp

    wp.config.quiet = True
    import newton

    rest = np.asarray(rest, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    builder = newton.ModelBuilder(gravity=tuple(float(g) for g in gravity))
    if ground is not None:
        cfg = newton.ModelBuilder.ShapeConfig()
        cfg.ke, cfg.kd, cfg.mu = CONTACT_KE, CONTACT_KD, float(ground)
        builder.add_ground_plane(cfg=cfg)
        radius = GROUND_PARTICLE_RADIUS
    else:
        edge = float(np.min(np.linalg.norm(rest[tets[:, 1]] - rest[tets[:, 0]], axis=1)))
        radius = 1e-3 * edge
    builder.add_soft_mesh(
        pos=wp.vec3(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=wp.vec3(0.0, 0.0, 0.0),
        vertices=[wp.vec3(*p) for p in rest],  # the REST shape: Newton's tet_poses come from these
        indices=tets.astype(np.int32).ravel().tolist(),
        density=density,
        k_mu=mu,
        k_lambda=lam,
        k_damp=0.0,
        particle_radius=radius,
    )
    if solver == "vbd":
        builder.color()  # VBD's vertex colouring (Gauss-Seidel in parallel per colour)
    with wp.ScopedDevice("cpu"):
        model = builder.finalize(device="cpu")
    # No particle-particle contact (its hash grid is rebuilt every step otherwise).
    model.particle_grid = None
    if solver == "xpbd":
        # XPBD solves particle-particle contact whenever particle_max_radius > 0 (and then asserts a grid): off,
        # as for the other solvers; the per-particle radius still sets the ground contact distance.
        model.particle_max_radius = 0.0
    if ground is not None:
        model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = CONTACT_KE, CONTACT_KD, float(ground)
    return model


def make_solver(model, solver, iterations=10):
    import newton

    if solver == "semi_implicit":
        return newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
    if solver == "vbd":
        return newton.solvers.SolverVBD(model, iterations=iterations)
    if solver == "xpbd":
        return newton.solvers.SolverXPBD(model, iterations=iterations)
    raise ValueError(solver)


class Run:
    """A solver, its two states (the first one holding ``x0``) and the collision pipeline when there is a shape."""

    def __init__(self, model, x0, solver, iterations=10):
        import newton
        import warp as wp

        self.model = model
        self.solver = make_solver(model, solver, iterations)
        self.s0, self.s1 = model.state(), model.state()
        q = wp.array(np.asarray(x0, dtype=np.float32), dtype=wp.vec3, device="cpu")
        self.s0.particle_q.assign(q)  # the deformed start; the model keeps the rest shape
        self.s0.particle_qd.zero_()
        self.control = model.control()
        if model.shape_count:
            self.pipeline = newton.CollisionPipeline(model)
            self.contacts = self.pipeline.contacts()
        else:
            self.pipeline = self.contacts = None

    def step(self, dt, n=1):
        for _ in range(n):
            self.s0.clear_forces()  # the semi-implicit solver accumulates into state_in.particle_f
            if self.pipeline is not None:
                self.pipeline.collide(self.s0, self.contacts)
            self.solver.step(self.s0, self.s1, self.control, self.contacts, dt)
            self.s0, self.s1 = self.s1, self.s0

    def positions(self):
        return self.s0.particle_q.numpy().astype(np.float64)

    def masses(self):
        return self.model.particle_mass.numpy().astype(np.float64)


def time_step(rest, tets, mu, lam, density, x0, dt, budget_s=1.0, min_steps=3, solver="semi_implicit"):
    """Seconds per step of Newton's solver on the CPU from the deformed start ``x0``, after a warm-up step
    (which compiles the kernels), and whether the state stayed finite."""
    import warp as wp

    model = build(rest, tets, mu, lam, density, solver=solver)
    with wp.ScopedDevice("cpu"):
        run = Run(model, x0, solver)
        run.step(dt)  # compiles the kernels
        wp.synchronize()
        n, t0 = 0, time.perf_counter()
        while n < min_steps or time.perf_counter() - t0 < budget_s:
            run.step(dt)
            n += 1
        wp.synchronize()
        per_step = (time.perf_counter() - t0) / n
        ok = bool(np.all(np.isfinite(run.positions())))
    return per_step, ok


def simulate(
    rest, tets, mu, lam, density, x0, dt, duration, *, solver, gravity=(0.0, 0.0, 0.0), ground=None,
    iterations=10, frame=None, max_steps=None, wall_budget_s=None,
):  # fmt: skip
    """Runs ``duration`` seconds (or ``max_steps``) from ``x0`` and returns the time per step (the solver's steps
    and collision only: a warm-up run compiles the kernels first, the quality checks are outside the timing)
    with the quality figures of ``quality.Quality`` sampled every ``frame`` seconds of scene time. With
    ``wall_budget_s`` the run stops early once its steps have taken that long (``steps`` < ``steps_planned``)."""
    import warp as wp
    from quality import Quality, timed_run

    model = build(rest, tets, mu, lam, density, solver=solver, gravity=gravity, ground=ground)
    with wp.ScopedDevice("cpu"):
        warm = Run(model, x0, solver, iterations)
        warm.step(dt, 2)  # compiles the kernels (a fresh run is timed)
        wp.synchronize()
        run = Run(model, x0, solver, iterations)
        q = Quality(rest, tets, run.masses(), ref=x0)
        steps = int(round(duration / dt))
        if max_steps is not None:
            steps = min(steps, max_steps)
        every = max(1, int(round((frame or dt) / dt)))
        def step(n):
            run.step(dt, n)
            wp.synchronize()

        t_steps, done = timed_run(
            step, run.positions, q, steps=steps, every=every, wall_budget_s=wall_budget_s
        )
        out = q.summary(run.positions())
    out.update(steps=done, steps_planned=steps, dt=dt, ms_per_step=1e3 * t_steps / max(done, 1))
    out["mass"] = float(run.masses().sum())
    return out


def largest_stable_dt(rest, tets, mu, lam, density, x0, dt, *, solver, steps=300, halvings=14, **kw):
    """The largest of dt, dt/2, dt/4, ... at which ``steps`` steps from the deformed start ``x0`` (no gravity, no
    contact) stay bounded: finite, no vertex moving more than a quarter of the body's extent, and at most 0.1% of
    the tets inverted at any sampled state (10 samples). Newton's explicit and XPBD solvers blow up at a game
    step on these meshes. Returns the dt (None if none) and what each tried dt did."""
    extent = float(np.ptp(np.asarray(rest), axis=0).max())
    tried = []
    for _ in range(halvings):
        r = simulate(rest, tets, mu, lam, density, x0, dt, steps * dt, solver=solver, frame=dt * steps / 10, **kw)
        ok = r["finite"] and r["max_displacement"] < 0.25 * extent and r["inverted_worst"] <= 1e-3 * len(tets)
        tried.append(
            {"dt": dt, "finite": r["finite"], "inverted_worst": r["inverted_worst"],
             "max_displacement": r["max_displacement"], "ms_per_step": r["ms_per_step"]}
        )  # fmt: skip
        if ok:
            return dt, tried
        dt *= 0.5
    return None, tried
