"""PBAT (``pip install pbatoolkit``, CPU build): its hyperelastic energy + gradient of a tet mesh (Stable
Neo-Hookean, the energy it implements; one quadrature point per linear tet) and its VBD and XPBD steps."""

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


def time_vbd_step(rest, tets, mu, lam, density, x0, dt, iterations=10, budget_s=1.0, min_steps=2):
    """Seconds per VBD step (``iterations`` iterations, one substep), after a warm-up step."""
    pbat, fem, element, X, E = _fem(rest, tets)
    vbd = pbat.pbat.sim.vbd
    k = E.shape[1]
    # Boundary faces (for its contact data; no obstacles here).
    faces = {}
    for t in np.asarray(tets):
        for f in ((t[1], t[2], t[3]), (t[0], t[3], t[2]), (t[0], t[1], t[3]), (t[0], t[2], t[1])):
            key = tuple(sorted(f))
            faces[key] = None if key in faces else f
    F = np.array([f for f in faces.values() if f is not None], dtype=np.int64).T
    V = np.unique(F)
    data = (
        vbd.Data()
        .with_volume_mesh(np.asarray(x0, dtype=np.float64).T.copy(order="F"), E)
        .with_surface_mesh(V, F)
        .with_material(np.full(k, density), np.full(k, mu), np.full(k, lam))
        .construct(validate=False)
    )
    integ = vbd.Integrator(data)
    integ.step(dt, iterations)
    n, t0 = 0, time.perf_counter()
    while n < min_steps or time.perf_counter() - t0 < budget_s:
        integ.step(dt, iterations)
        n += 1
    return (time.perf_counter() - t0) / n
