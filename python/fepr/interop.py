"""The current state of a simulation as the Python ecosystem's mesh objects: meshio and PyVista.

:func:`to_meshio` gives a ``meshio.Mesh`` (points at the current positions, one ``tetra`` cell block) with the
fields a user plots or writes: per point ``velocity`` (m/s) and ``displacement`` (m, from the rest shape), per
cell ``J`` (``det F``, ``<= 0``: inverted) and ``energy_density`` (the material's ``Psi(F)``, J/m^3). Writing it
with ``meshio.write`` gives any format meshio knows. :func:`to_pyvista` gives the same as a
``pyvista.UnstructuredGrid`` (``pip install pyvista``), through PyVista's own meshio conversion. The fields are
those the exports write (:class:`fepr.export.Frame`), so a file written either way holds the same numbers.
"""

from __future__ import annotations

import numpy as np

from .errors import MissingDependencyError

__all__ = ["to_meshio", "to_pyvista"]


def to_meshio(sim):
    """The current state of ``sim`` (a :class:`fepr.Simulation` or :class:`fepr.MultiBody`, its bodies
    concatenated) as a ``meshio.Mesh`` with point data ``velocity``, ``displacement`` and cell data ``J``,
    ``energy_density`` (see the module docs)."""
    import meshio

    from .export.fields import Frame, TetKinematics

    bodies = getattr(sim, "bodies", None) or [sim]
    points, velocity, displacement, tets, j, psi = [], [], [], [], [], []
    offset = 0
    for body in bodies:
        frame = Frame.from_simulation(body, TetKinematics(body.rest_positions, body.tets))
        points.append(frame.positions)
        velocity.append(frame.velocities)
        displacement.append(frame.displacement)
        tets.append(np.asarray(frame.tets, dtype=np.int64) + offset)
        j.append(frame.volume_ratio)
        psi.append(frame.energy_density)
        offset += len(frame.positions)
    return meshio.Mesh(
        np.concatenate(points),
        [("tetra", np.concatenate(tets))],
        point_data={"velocity": np.concatenate(velocity), "displacement": np.concatenate(displacement)},
        cell_data={"J": [np.concatenate(j)], "energy_density": [np.concatenate(psi)]},
    )


def to_pyvista(sim):
    """The current state of ``sim`` as a ``pyvista.UnstructuredGrid`` with the fields of :func:`to_meshio`.

    Raises
    ------
    fepr.MissingDependencyError
        If PyVista is not installed (``pip install pyvista``, or ``pip install "fepr[pyvista]"``).
    """
    try:
        import pyvista
    except ImportError:
        raise MissingDependencyError(
            'to_pyvista needs PyVista: pip install pyvista (or pip install "fepr[pyvista]")'
        ) from None
    return pyvista.from_meshio(to_meshio(sim))
