"""Exception types of fepr. Every error names the problem so that a user can act on it."""


class FeprError(Exception):
    """Base class of all fepr errors."""


class MeshError(FeprError, ValueError):
    """A mesh is invalid or a mesh file cannot be read.

    The message names the file (when there is one), the line or element and the problem.
    """


class ConfigError(FeprError, ValueError):
    """A parameter or a scene file entry is invalid (the message names the key or parameter)."""


class SimulationError(FeprError, RuntimeError):
    """A simulation cannot continue, e.g. the state became non-finite (runaway of an unstable step).

    ``step`` (when set) is the number of the step that failed; the simulation stays at the step before it.
    """

    step: "int | None" = None


class MissingDependencyError(FeprError, ImportError):
    """An optional package that a feature needs is not installed (the message says what to install).

    For example :func:`fepr.tetrahedralize` needs the ``mesh`` extra: ``pip install "fepr[mesh]"``.
    """


class CheckpointError(FeprError, ValueError):
    """A checkpoint cannot be read or does not fit: not a fepr checkpoint, damaged, written by another checkpoint
    version, or for another mesh or settings (the message names the file and what does not match)."""


class ImplausibleValueWarning(UserWarning):
    """A parameter is computable but physically implausible, e.g. a density of 1e7 kg/m^3 or a time step of 10 s:
    usually a units mistake. The message names the parameter, its value, the plausible range and why.

    ``parameter`` is the parameter's name (``"density"``, ``"youngs_modulus"``, ``"dt"``); the bounds are in
    :data:`fepr._validate.PLAUSIBLE`. Silence it with ``warnings.simplefilter("ignore", ImplausibleValueWarning)``.
    """

    parameter: str = ""
