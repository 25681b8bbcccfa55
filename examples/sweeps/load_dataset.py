"""Load a fepr sweep dataset with NumPy alone (no fepr needed) and look at it.

    python examples/sweeps/load_dataset.py out/dataset/dataset      # a dataset written by `fepr sweep --dataset`
    python examples/sweeps/load_dataset.py --build out/dataset      # first write one from examples/sweeps/dataset.toml

Prints the split, the shape of one trajectory, and per split the mean kinetic energy at the first and last frame
(from the velocities and vertex masses), then builds the (frames - 1) training pairs x_t -> x_{t+1} of the first
training trajectory, as a one-step learned simulator would consume them.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np


def load(dataset: Path) -> dict:
    """Every trajectory of the dataset in ``dataset`` (its metadata rows, meshes and arrays, loaded lazily)."""
    info = json.loads((dataset / "dataset.json").read_text(encoding="utf-8"))
    with open(dataset / "metadata.csv", encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    meshes = {}
    for r in rows:
        if r["mesh_id"] not in meshes:
            with np.load(dataset / "meshes" / f"{r['mesh_id']}.npz") as z:
                meshes[r["mesh_id"]] = {"rest_positions": z["rest_positions"], "tets": z["tets"]}
    return {"info": info, "rows": rows, "meshes": meshes}


def trajectory(dataset: Path, row: dict) -> dict:
    """One trajectory: positions and velocities (frames, m, 3) [m, m/s], masses (m,) [kg]."""
    out = {
        "positions": np.load(dataset / "positions" / f"{row['run_id']}.npy", mmap_mode="r"),
        "masses": np.load(dataset / "masses" / f"{row['run_id']}.npy"),
    }
    v = dataset / "velocities" / f"{row['run_id']}.npy"
    if v.is_file():
        out["velocities"] = np.load(v, mmap_mode="r")
    return out


def main(argv: list) -> int:
    if argv and argv[0] == "--build":
        import fepr.sweep  # only to write the dataset; reading it needs NumPy alone

        out = Path(argv[1] if len(argv) > 1 else "out/dataset")
        spec = Path(__file__).with_name("dataset.toml")
        index = fepr.sweep.run_sweep(spec, out, dataset=True, progress=False)
        print(fepr.sweep.summary_line(index.attrs["sweep"]))
        dataset = out / "dataset"
    elif argv:
        dataset = Path(argv[0])
    else:
        print(__doc__)
        return 2
    data = load(dataset)
    rows = data["rows"]
    counts = data["info"]["split"]["counts"]
    print(f"{dataset}: {len(rows)} trajectories, split {counts}, {len(data['meshes'])} mesh(es)")
    first = trajectory(dataset, rows[0])
    x = first["positions"]
    mesh = data["meshes"][rows[0]["mesh_id"]]
    print(
        f"trajectory {rows[0]['run_id']}: (frames, m, 3) = {x.shape}, tets {mesh['tets'].shape}, "
        f"frame_dt {float(rows[0]['frame_dt_s']):.4g} s"
    )
    for split in ("train", "validation", "test"):
        ks = [r for r in rows if r["split"] == split]
        if not ks or "velocities" not in first:
            continue
        energy = []
        for r in ks:
            t = trajectory(dataset, r)
            ke = 0.5 * np.einsum("i,fij,fij->f", t["masses"], t["velocities"], t["velocities"])
            energy.append((ke[0], ke[-1]))
        e = np.mean(energy, axis=0)
        print(
            f"{split:>10}: {len(ks):3d} trajectories, mean kinetic energy {e[0]:.4g} J at the start, "
            f"{e[1]:.4g} J at the end"
        )
    train = [r for r in rows if r["split"] == "train"]
    if train:
        x = trajectory(dataset, train[0])["positions"]
        inputs, targets = np.asarray(x[:-1]), np.asarray(x[1:])  # one-step pairs: x_t -> x_{t+1}
        print(f"one-step pairs of {train[0]['run_id']}: inputs {inputs.shape}, targets {targets.shape}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
