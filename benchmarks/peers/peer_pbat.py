"""PBAT (``pip install pbatoolkit``, CPU build): its hyperelastic energy + gradient of a tet mesh (Stable
Neo-Hookean, the energy it implements; one quadrature point per linear tet) and its VBD step.

``vbd.Data().with_volume_mesh(X, T)`` takes the **rest shape** X (the element rest matrices and masses come
from it): the deformed start is written into the integrator's ``x`` afterwards. ``vbd.Data``'s external
acceleration defaults to gravity (-9.81 along z); the elastic-only scenes set it to zero with
``with_acceleration``. (Before round 15 the stretched positions were passed as X, under gravity.)"""

from __future__ import annotations

import time

import numpy as np


def _fem(rest, tets):
    import pbatoolkit as pbat

    fem = pbat.pbat.fem
    element = fem.Element.Tetrahedron
    X, E = fem.mesh(
        np.asarray(rest, dtype=np.float64).T.copy(order="F"),
        np.asarray(tets, dtype=np.int64).T.copy(order="F"),
        element=element,
    )
    return pbat, fem, element, X, E


def time_energy_gradient(rest, tets, mu, lam, x0, budget_s=1.0, min_reps=3):
    """Seconds per energy + gradient evaluation (PBAT's own threading), after one warm-up evaluation."""
    pbat, fem, element, X, E = _fem(rest, tets)
    wg = fem.mesh_quadrature_weights(E, X, element, order=1, quadrature_order=1)
    eg = fem.mesh_quadrature_elements(E, wg)
    gneg = fem.shape_function_gradients(E, X, element=element, order=1, dims=3, quadrature_order=1)
    mug = np.full(wg.size, mu)
    lambdag = np.full(wg.size, lam)
    x = np.ravel(np.asarray(x0, dtype=np.float64).T, order="F")  # (3, m) column-major = x0 row-major

    def evaluate():
        u, g, _ = fem.hyper_elastic_potential(
            E=E,
            n_nodes=X.shape[1],
            eg=np.ravel(eg),
            wg=np.ravel(wg),
            GNeg=gneg,
            mug=mug,
            lambdag=lambdag,
            x=x,
            energy=fem.HyperElasticEnergy.StableNeoHookean,
            flags=fem.ElementElasticityComputationFlags.Potential | fem.ElementElasticityComputationFlags.Gradient,
            spd_correction=fem.HyperElasticSpdCorrection.NoCorrection,
            element=element,
            order=1,
            dims=3,
        )
        return u, g

    evaluate()
    n, t0 = 0, time.perf_counter()
    while n < min_reps or time.perf_counter() - t0 < budget_s:
        evaluate()
        n += 1
    return (time.perf_counter() - t0) / n


def _surface(tets):
    """Boundary faces (for VBD's contact data; no obstacles here): V (vertex ids) and F (3 x faces)."""
    faces = {}
    for t in np.asarray(tets):
        for f in ((t[1], t[2], t[3]), (t[0], t[3], t[2]), (t[0], t[1], t[3]), (t[0], t[2], t[1])):
            key = tuple(sorted(f))
            faces[key] = None if key in faces else f
    F = np.array([f for f in faces.values() if f is not None], dtype=np.int64).T
    return np.unique(F), F


def vbd_integrator(rest, tets, mu, lam, density, x0, gravity=(0.0, 0.0, 0.0)):
    """PBAT's VBD integrator built on the rest shape, its state set to x0 (zero velocity)."""
    pbat, fem, element, X, E = _fem(rest, tets)
    vbd = pbat.pbat.sim.vbd
    k = E.shape[1]
    V, F = _surface(tets)
    n = np.asarray(rest).shape[0]
    data = (
        vbd.Data()
        .with_volume_mesh(np.asarray(rest, dtype=np.float64).T.copy(order="F"), E)  # the REST shape
        .with_surface_mesh(V, F)
        .with_material(np.full(k, density), np.full(k, mu), np.full(k, lam))
        .with_acceleration(np.repeat(np.asarray(gravity, dtype=np.float64)[:, None], n, axis=1))
        .construct(validate=False)
    )
    integ = vbd.Integrator(data)
    integ.x = np.asarray(x0, dtype=np.float64).T.copy(order="F")  # the deformed start
    return integ


def time_vbd_step(rest, tets, mu, lam, density, x0, dt, iterations=10, budget_s=1.0, min_steps=2):
    """Seconds per VBD step (``iterations`` iterations, one substep) from the deformed start, after a warm-up
    step."""
    integ = vbd_integrator(rest, tets, mu, lam, density, x0)
    integ.step(dt, iterations)
    n, t0 = 0, time.perf_counter()
    while n < min_steps or time.perf_counter() - t0 < budget_s:
        integ.step(dt, iterations)
        n += 1
    return (time.perf_counter() - t0) / n


def simulate(
    rest,
    tets,
    mu,
    lam,
    density,
    x0,
    dt,
    duration,
    iterations=10,
    frame=None,
    max_steps=None,
    wall_budget_s=None,
    masses=None,
):
    """``duration`` seconds of VBD from x0 (no gravity, no obstacle): ms per step (the steps only) and the
    quality figures of ``quality.Quality`` sampled every ``frame`` seconds of scene time."""
    from quality import Quality, timed_run

    integ = vbd_integrator(rest, tets, mu, lam, density, x0)
    q = Quality(rest, tets, masses, ref=x0)  # masses: for the centre of mass (PBAT lumps rho V / 4 too)
    steps = int(round(duration / dt))
    if max_steps is not None:
        steps = min(steps, max_steps)
    every = max(1, int(round((frame or dt) / dt)))
    def step(n):
        for _ in range(n):
            integ.step(dt, iterations)

    t_steps, done = timed_run(
        step, lambda: np.asarray(integ.x).T, q, steps=steps, every=every, wall_budget_s=wall_budget_s
    )
    out = q.summary(np.asarray(integ.x).T.copy())
    out.update(steps=done, steps_planned=steps, dt=dt, ms_per_step=1e3 * t_steps / max(done, 1))
    return out
