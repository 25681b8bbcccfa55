"""glTF 2.0 binary (``.glb``): the boundary surface animated with one morph target per frame.

Structure (what Blender's stock glTF importer turns into shape keys and a shape-key action):

- one node with one mesh with one triangle primitive: the boundary surface at the first frame (``POSITION``,
  ``uint32`` indices, outward counter-clockwise winding) and one morph target per later frame, whose
  ``POSITION`` is the displacement of that frame from the first;
- ``mesh.extras.targetNames`` names the targets ``frame_00001``, ``frame_00002``, ... (the shape key names);
- one animation ``simulation`` with a single ``weights`` channel keyed at the frame times (seconds from the
  first frame, so playback is in real simulated time): at frame ``i`` the weights are one-hot on target ``i``
  (all zero at frame 0). With ``LINEAR`` interpolation (the default) the weights between two keys are
  ``1 - s`` and ``s`` on two consecutive targets, which is exactly the linear interpolation of the vertex
  positions of the two frames: playback at any frame rate is smooth, and a key that lands a rounding error
  away from an integer frame of the player still shows its frame. ``STEP`` shows each frame unchanged until
  the next one, but a key time rounded (float32) just past an integer frame of the player is then shown one
  player frame late.

glTF is +Y up and fepr's scenes are +Z up, so positions are written as ``(x, z, -y)`` (a rotation, which keeps
the winding): importers that convert glTF to +Z up (Blender does) show the body the way up it was simulated.
Units are metres. Every ``POSITION`` accessor and the animation's time accessor carry exact ``min``/``max``;
buffer views are 4-byte aligned. The document and the GLB container (header, chunks, padding) are pygltflib's:
fepr only packs the arrays.

Size: about ``12 V N`` bytes for ``N`` frames of ``V`` surface vertices plus ``4 N^2`` bytes of weights (the
weights of all targets at every key); keep ``N`` to a few hundred frames (``every``) for long runs.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import pygltflib as gl

from ..errors import ConfigError
from ..io.atomic import atomic_path
from .base import FrameWriter, PathLike
from .fields import Frame

__all__ = ["GlbWriter", "Z_UP_TO_Y_UP", "glb_accessor", "read_glb", "write_glb"]

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPES = {gl.BYTE: "<i1", gl.UNSIGNED_BYTE: "<u1", gl.SHORT: "<i2", gl.UNSIGNED_SHORT: "<u2",
           gl.UNSIGNED_INT: "<u4", gl.FLOAT: "<f4"}  # fmt: skip

#: Rotation taking fepr's +Z-up coordinates to glTF's +Y-up ones: ``(x, y, z) -> (x, z, -y)``.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class _Buffer:
    """The binary buffer under construction: one 4-byte aligned buffer view and one accessor per array."""

    def __init__(self) -> None:
        self.parts: List[bytes] = []
        self.length = 0
        self.views: List[gl.BufferView] = []
        self.accessors: List[gl.Accessor] = []

    def accessor(self, data: np.ndarray, kind: str, *, target: Optional[int] = None, bounds: bool = False) -> int:
        a = np.ascontiguousarray(data)
        a, ctype = (a.astype("<f4"), gl.FLOAT) if a.dtype.kind == "f" else (a.astype("<u4"), gl.UNSIGNED_INT)
        raw = a.tobytes()
        self.views.append(gl.BufferView(buffer=0, byteOffset=self.length, byteLength=len(raw), target=target))
        pad = (-len(raw)) % 4
        self.parts.append(raw + b"\0" * pad)
        self.length += len(raw) + pad
        comps = _COMPONENTS[kind]
        acc = gl.Accessor(bufferView=len(self.views) - 1, componentType=ctype, count=int(a.size // comps), type=kind)
        if bounds and a.size:
            flat = a.reshape(-1, comps)
            # float32 values are exactly representable as Python floats, so min/max match the stored data.
            acc.min = [float(v) for v in flat.min(axis=0)]
            acc.max = [float(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def data(self) -> bytes:
        return b"".join(self.parts)


def write_glb(
    path: PathLike,
    frames: np.ndarray,
    faces: np.ndarray,
    times: np.ndarray,
    *,
    name: str = "fepr",
    z_up: bool = True,
    interpolation: str = "LINEAR",
    extras: Optional[Dict[str, Any]] = None,
) -> Path:
    """Write an animated triangle surface as a ``.glb`` (the structure of the module docstring).

    Parameters
    ----------
    path : str or Path
        Output file.
    frames : (N, V, 3) float
        Vertex positions of every frame, m.
    faces : (F, 3) int
        Triangles as indices into the V vertices, counter-clockwise seen from outside.
    times : (N,) float
        Frame times, s, strictly increasing; the animation starts at 0 (``times - times[0]``).
    name : str
        Name of the node, mesh and (with ``_surface``) nothing else; Blender names the object after it.
    z_up : bool
        The positions are +Z up: rotate them to glTF's +Y up (default). ``False`` writes them unchanged.
    interpolation : str
        ``"LINEAR"`` (default) or ``"STEP"`` for the weights animation.
    extras : dict, optional
        JSON-serialisable data stored in the file's top-level ``extras``.
    """
    if interpolation not in ("LINEAR", "STEP"):
        raise ConfigError(f"interpolation must be 'LINEAR' or 'STEP', got {interpolation!r}")
    pos = np.asarray(frames, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 1:
        raise ConfigError(f"frames must have shape (N, V, 3) with N >= 1, got {pos.shape}")
    tri = np.asarray(faces, dtype=np.int64)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ConfigError(f"faces must have shape (F, 3), got {tri.shape}")
    n, v = pos.shape[0], pos.shape[1]
    if tri.size and (tri.min() < 0 or tri.max() >= v):
        raise ConfigError(f"faces index vertices outside 0..{v - 1}")
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.shape != (n,):
        raise ConfigError(f"times must have shape ({n},), got {t.shape}")
    t32 = (t - t[0]).astype("<f4")
    if n > 1 and not np.all(np.diff(t32) > 0):
        raise ConfigError("frame times must be strictly increasing (as float32 seconds from the first frame)")
    if z_up:
        pos = pos @ Z_UP_TO_Y_UP.T
    base = pos[0].astype("<f4")

    buf = _Buffer()
    i_idx = buf.accessor(tri.reshape(-1), "SCALAR", target=gl.ELEMENT_ARRAY_BUFFER)
    i_pos = buf.accessor(base, "VEC3", target=gl.ARRAY_BUFFER, bounds=True)
    targets = []
    for k in range(1, n):
        delta = (pos[k] - base.astype(np.float64)).astype("<f4")
        targets.append({"POSITION": buf.accessor(delta, "VEC3", target=gl.ARRAY_BUFFER, bounds=True)})
    primitive = gl.Primitive(attributes=gl.Attributes(POSITION=i_pos), indices=i_idx, mode=gl.TRIANGLES, material=0)
    mesh = gl.Mesh(name=name, primitives=[primitive])
    doc = gl.GLTF2(
        asset=gl.Asset(version="2.0", generator=f"fepr {_version()}"),
        scene=0,
        scenes=[gl.Scene(name=name, nodes=[0])],
        nodes=[gl.Node(name=name, mesh=0)],
        meshes=[mesh],
        materials=[
            gl.Material(
                name="fepr_body",
                pbrMetallicRoughness=gl.PbrMetallicRoughness(
                    baseColorFactor=[0.80, 0.50, 0.25, 1.0], metallicFactor=0.0, roughnessFactor=0.6
                ),
            )
        ],
    )
    if targets:
        primitive.targets = targets
        mesh.weights = [0.0] * len(targets)
        mesh.extras = {"targetNames": [f"frame_{k:05d}" for k in range(1, n)]}
        weights = np.zeros((n, n - 1), dtype="<f4")
        weights[np.arange(1, n), np.arange(n - 1)] = 1.0
        i_in = buf.accessor(t32, "SCALAR", bounds=True)
        i_out = buf.accessor(weights.reshape(-1), "SCALAR")
        doc.animations = [
            gl.Animation(
                name="simulation",
                samplers=[gl.AnimationSampler(input=i_in, output=i_out, interpolation=interpolation)],
                channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(node=0, path="weights"))],
            )
        ]
    doc.buffers = [gl.Buffer(byteLength=buf.length)]
    doc.bufferViews = buf.views
    doc.accessors = buf.accessors
    if extras:
        doc.extras = extras
    doc.set_binary_blob(buf.data())
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(b"".join(doc.save_to_bytes()))
    return out


def _version() -> str:
    try:
        from .. import __version__

        return str(__version__)
    except ImportError:  # pragma: no cover
        return "unknown"


def read_glb(path: PathLike) -> Tuple[Dict[str, Any], bytes]:
    """Parse a ``.glb``: ``(gltf JSON as a dict, binary chunk)`` (pygltflib reads the container).

    Checks first what pygltflib takes on trust, so that a damaged file is an error naming the file: the header
    (magic, version 2, total length equal to the file size), and that buffer 0 fits in the binary chunk.

    Raises
    ------
    ConfigError
        If a check fails or pygltflib cannot parse the file.
    """
    p = Path(path)
    data = p.read_bytes()

    def bad(msg: str) -> ConfigError:
        return ConfigError(f"{p}: not a valid .glb: {msg}")

    if len(data) < 20:
        raise bad(f"only {len(data)} bytes")
    magic, version, total = struct.unpack_from("<III", data, 0)
    if data[:4] != b"glTF":
        raise bad("wrong magic")
    if version != 2:
        raise bad(f"version {version}, expected 2")
    if total != len(data):
        raise bad(f"header length {total} != file size {len(data)}")
    try:
        doc = gl.GLTF2.load_from_bytes(data)
    except Exception as exc:  # pygltflib raises whatever its parser meets (struct, JSON, key errors)
        raise bad(str(exc)) from None
    binary = doc.binary_blob() or b""
    gltf = json.loads(doc.to_json())  # plain JSON types, empty fields left out (as in the file)
    buffers = gltf.get("buffers", [])
    if buffers and buffers[0].get("byteLength", 0) > len(binary):
        raise bad("buffer 0 is longer than the BIN chunk")
    return gltf, binary


def glb_accessor(gltf: Dict[str, Any], binary: bytes, index: int) -> np.ndarray:
    """The data of accessor ``index`` as an array of shape (count,) or (count, components).

    Handles the layouts this module writes (tightly packed views in buffer 0, no sparse storage).
    """
    acc = gltf["accessors"][index]
    view = gltf["bufferViews"][acc["bufferView"]]
    comps = _COMPONENTS[acc["type"]]
    dtype = np.dtype(_DTYPES[acc["componentType"]])
    if view.get("byteStride") not in (None, comps * dtype.itemsize):
        raise ConfigError("strided buffer views are not supported")
    offset = (view.get("byteOffset") or 0) + (acc.get("byteOffset") or 0)
    count = acc["count"] * comps
    if offset + count * dtype.itemsize > (view.get("byteOffset") or 0) + view["byteLength"]:
        raise ConfigError(f"accessor {index} runs past its buffer view")
    a = np.frombuffer(binary, dtype=dtype, count=count, offset=offset)
    return a if comps == 1 else a.reshape(-1, comps)


class GlbWriter(FrameWriter):
    """Collects the boundary surface of every frame and writes one animated ``.glb`` at :meth:`close`.

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation to record.
    path : str or Path
        The ``.glb`` file.
    name : str, optional
        Node and mesh name (Blender's object name); default the file's stem.
    z_up : bool
        Rotate +Z up to glTF's +Y up (default ``True``; see the module docstring).
    interpolation : str
        ``"LINEAR"`` (default: positions interpolated between frames) or ``"STEP"``.

    The positions are kept in memory (float32, ``12 V`` bytes per frame) until :meth:`close`.
    """

    format = "glb"

    def __init__(
        self,
        sim,
        path: PathLike,
        *,
        name: Optional[str] = None,
        z_up: bool = True,
        interpolation: str = "LINEAR",
        **kw,
    ):
        if interpolation not in ("LINEAR", "STEP"):
            raise ConfigError(f"interpolation must be 'LINEAR' or 'STEP', got {interpolation!r}")
        super().__init__(sim, **kw)
        self.interpolation = interpolation
        self.path = Path(path)
        self.name = name or self.path.stem
        self.z_up = z_up
        self._frames: List[np.ndarray] = []
        self._times: List[float] = []
        self._steps: List[int] = []

    def _write(self, frame: Frame) -> None:
        if self._times and not frame.time > self._times[-1]:
            raise ConfigError(
                f"glb frames need increasing times: frame at t = {frame.time!r} s after t = {self._times[-1]!r} s"
            )
        self._frames.append(frame.positions[self.surface.vertices].astype(np.float64))
        self._times.append(frame.time)
        self._steps.append(frame.step)

    def _finish(self) -> None:
        if not self._frames:
            return
        with atomic_path(self.path) as tmp:
            self._write_glb(tmp)
        self._frames = []

    def _write_glb(self, path) -> None:
        write_glb(
            path,
            np.stack(self._frames),
            self.surface.local_faces,
            np.asarray(self._times),
            name=self.name,
            z_up=self.z_up,
            interpolation=self.interpolation,
            extras={
                "fepr": {
                    "frames": len(self._frames),
                    "steps": self._steps,
                    "times": self._times,
                    "up_axis": "rotated +Z to +Y" if self.z_up else "unchanged",
                }
            },
        )

    def paths(self) -> List[Path]:
        return [self.path] if self.closed and self.path.exists() else []
