"""Plot time per tet against mesh size from a ``fepr bench --json`` file (the box scenes):

python benchmarks/plot_scaling.py benchmarks/results/bench.json benchmarks/results/scaling.png
"""

from __future__ import annotations

import json
import sys


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    argv = sys.argv[1:] if argv is None else argv
    src, dst = argv[0], argv[1]
    doc = json.loads(open(src).read())
    boxes = sorted(
        (s for s in doc["scenes"] if s["scene"].startswith("box_") and "energy_gradient" in s), key=lambda s: s["tets"]
    )
    tets = [s["tets"] for s in boxes]
    eg1 = [s["energy_gradient"]["ns_per_tet_1_thread"] for s in boxes]
    egn = [s["energy_gradient"]["ns_per_tet_all_threads"] for s in boxes]
    step = [1e6 * s["integrators"][0]["ms_per_step"] / s["tets"] for s in boxes]
    base = [1e6 * s["integrators"][0]["base_ms"] / s["tets"] for s in boxes]
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=110)
    ax.plot(tets, eg1, "o-", label="energy + gradient, 1 thread")
    ax.plot(tets, egn, "o-", label=f"energy + gradient, {doc['machine']['cpus']} threads")
    ax.plot(tets, base, "s--", label="symplectic Euler step (base)")
    ax.plot(tets, step, "s-", label="symplectic Euler + FEPR step")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("tets (built-in box)")
    ax.set_ylabel("ns per tet")
    ax.set_title("fepr bench: time per tet vs mesh size")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(dst)
    return 0


if __name__ == "__main__":
    sys.exit(main())
