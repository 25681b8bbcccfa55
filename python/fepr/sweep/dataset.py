"""A sweep's trajectories as a dataset for a learned simulator (MeshGraphNets-style), readable with NumPy alone.

``fepr sweep SWEEP.toml --out DIR --dataset`` (or :func:`write_dataset` on a finished sweep) writes
``DIR/dataset/``::

    dataset.json               what is here: format, version, units, frames_every, split fractions and seed,
                               counts per split, the runs left out (ran away or failed) and why
    metadata.csv               one row per trajectory (see below)
    meshes/<mesh_id>.npz       rest_positions (m, 3) float64 [m], tets (k, 4) int64 (vertex indices, from 0)
    positions/<run_id>.npy     (frames, m, 3) float64 [m]: frame j is the state after j * frames_every steps
    velocities/<run_id>.npy    (frames, m, 3) float64 [m/s] (when the sweep records velocities)
    masses/<run_id>.npy        (m,) float64 [kg]: the lumped vertex masses (they follow the density)
    README.md                  this layout, and how to load it

``metadata.csv`` (UTF-8, a header row, ``,``-separated) has ``trajectory`` (0, 1, ... in the sweep's order),
``run_id``, ``split`` (``train``, ``validation`` or ``test``), ``mesh_id``, ``frames``, ``vertices``,
``frame_dt_s`` (simulated seconds between frames), ``dt_s`` (the time step), then one column per parameter of
the sweep (numbers as numbers, anything else as JSON text), then ``energy_error``, ``unresolved``, ``min_j``
and ``final_inverted`` of the run (:mod:`fepr.sweep.index`), to filter by quality.

Only runs that completed are in the dataset. The split is a permutation of them by ``numpy.random.default_rng(
seed)``, cut in the given fractions (``round(train * n)`` train, ``round(validation * n)`` validation, the rest
test): the same seed and runs give the same split. The trajectory files are hard links to the run folders'
arrays where the file system allows (no copy), else copies. The folder is derived: it is written anew (to a
temporary name, then renamed) each time.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError
from .index import read_index

__all__ = ["SPLITS", "write_dataset"]

SPLITS = ("train", "validation", "test")
_QUALITY = ("energy_error", "unresolved", "min_j", "final_inverted")
_FIXED = ("trajectory", "run_id", "split", "mesh_id", "frames", "vertices", "frame_dt_s", "dt_s")


def _link(src: Path, dst: Path) -> None:
    """A hard link (no copy), or a copy across file systems."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def _split_counts(n: int, split: Sequence[float]) -> Tuple[int, int, int]:
    train = int(round(split[0] * n))
    val = min(int(round(split[1] * n)), n - train)
    return train, val, n - train - val


def _cell(v: Any) -> Any:
    """A metadata cell: numbers and strings as they are, missing as empty, anything else as JSON text."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, float, str, np.integer, np.floating)):
        return v
    if isinstance(v, np.ndarray):
        v = v.tolist()
    return json.dumps(v, sort_keys=True)


_README = """# fepr dataset: {name}

{count} trajectories ({counts}) of the sweep `{name}`, written by `fepr sweep --dataset` (fepr {version}).

- `metadata.csv`: one row per trajectory (run_id, split, mesh_id, frames, frame_dt_s, parameters, quality)
- `meshes/<mesh_id>.npz`: `rest_positions` (m, 3) float64 [m], `tets` (k, 4) int64
- `positions/<run_id>.npy`: (frames, m, 3) float64 [m]; frame j is the state after j * {every} steps
- `velocities/<run_id>.npy`: (frames, m, 3) float64 [m/s]{no_velocities}
- `masses/<run_id>.npy`: (m,) float64 [kg]
- `dataset.json`: the same in JSON, with the split fractions and seed and the runs left out

Load it with NumPy alone:

```python
import csv, numpy as np
rows = list(csv.DictReader(open("metadata.csv", encoding="utf-8")))
train = [r for r in rows if r["split"] == "train"]
x = np.load(f"positions/{{train[0]['run_id']}}.npy")        # (frames, m, 3)
mesh = np.load(f"meshes/{{train[0]['mesh_id']}}.npz")       # rest_positions, tets
```
"""


def write_dataset(sweep_dir: Union[str, Path], *, split: Sequence[float] = (0.8, 0.1, 0.1), seed: int = 0) -> Path:
    """Write ``sweep_dir/dataset`` from a finished sweep (see the module docs); returns its path.

    Raises
    ------
    ConfigError
        If the sweep has no index, recorded no frames (``[sweep] frames_every``), or the split is not three
        fractions >= 0 that sum to 1.
    """
    from ..scene import load_scene

    out = Path(sweep_dir)
    if len(split) != 3 or any(f < 0 for f in split) or abs(sum(split) - 1.0) > 1e-9:
        raise ConfigError(f"split must be [train, validation, test], fractions >= 0 that sum to 1, got {list(split)}")
    df = read_index(out)
    manifest = json.loads((out / "sweep.json").read_text(encoding="utf-8"))
    every = int(manifest["sweep"]["frames_every"])
    if not every:
        raise ConfigError(f"{out}: the sweep recorded no frames; set [sweep] frames_every = K and run it again")
    done = df[(df["status"] == "complete") & (df["frames"] > 0)].sort_values("number")
    excluded = [
        {"run_id": r.run_id, "status": r.status, "error": r.error} for r in df[~df.index.isin(done.index)].itertuples()
    ]
    n = len(done)
    order = np.random.default_rng(seed).permutation(n)
    n_train, n_val, _ = _split_counts(n, split)
    split_of = np.empty(n, dtype=object)
    split_of[order[:n_train]] = "train"
    split_of[order[n_train : n_train + n_val]] = "validation"
    split_of[order[n_train + n_val :]] = "test"

    tmp = out / ".dataset.part"
    shutil.rmtree(tmp, ignore_errors=True)
    for sub in ("meshes", "positions", "velocities", "masses"):
        (tmp / sub).mkdir(parents=True)
    param_names = [c for c in df.columns[3 : list(df.columns).index("params")]]
    rows: List[Dict[str, Any]] = []
    velocities = bool(manifest["sweep"].get("frame_velocities", True))
    for k, r in enumerate(done.itertuples()):
        run = out / r.path
        row: Dict[str, Any] = {
            "trajectory": k,
            "run_id": r.run_id,
            "split": split_of[k],
            "mesh_id": r.mesh_id,
            "frames": int(r.frames),
            "vertices": int(r.vertices),
        }
        dt = load_scene(run / "scene.toml").integrator.dt
        row["frame_dt_s"], row["dt_s"] = every * dt, dt
        mesh_file = tmp / "meshes" / f"{r.mesh_id}.npz"
        if not mesh_file.exists():
            _link(out / "meshes" / f"{r.mesh_id}.npz", mesh_file)
        _link(run / "positions.npy", tmp / "positions" / f"{r.run_id}.npy")
        if velocities:
            _link(run / "velocities.npy", tmp / "velocities" / f"{r.run_id}.npy")
        with np.load(run / "final_state.npz") as z:
            np.save(tmp / "masses" / f"{r.run_id}.npy", np.asarray(z["masses"], dtype=np.float64))
        record = done.loc[r.Index]
        for name in param_names:
            row[name] = _cell(record[name])
        for name in _QUALITY:
            row[name] = _cell(record[name])
        rows.append(row)
    if not velocities:
        (tmp / "velocities").rmdir()
    columns = [*_FIXED, *param_names, *_QUALITY]
    with open(tmp / "metadata.csv", "w", encoding="utf-8", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    counts = {s: int(np.sum(split_of == s)) for s in SPLITS}
    info = {
        "format": "fepr-dataset",
        "version": 1,
        "fepr": manifest.get("fepr"),
        "sweep": manifest["sweep"]["name"],
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "frames_every": every,
        "velocities": velocities,
        "units": {"positions": "m", "velocities": "m/s", "masses": "kg", "frame_dt_s": "s", "dt_s": "s"},
        "split": {"fractions": dict(zip(SPLITS, map(float, split))), "seed": int(seed), "counts": counts},
        "trajectories": n,
        "columns": columns,
        "excluded": excluded,
    }
    (tmp / "dataset.json").write_text(json.dumps(info, indent=1) + "\n", encoding="utf-8")
    (tmp / "README.md").write_text(
        _README.format(
            name=info["sweep"],
            count=n,
            counts=", ".join(f"{v} {k}" for k, v in counts.items()),
            version=info["fepr"],
            every=every,
            no_velocities="" if velocities else " (not recorded by this sweep: the folder is absent)",
        ),
        encoding="utf-8",
    )
    final = out / "dataset"
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    return final
