"""The work a change of the intact bonds costs in a stochastic fracture run of the
crack-ensemble plate, piece by piece, with the compiled loops (``bayespd.bond_loops``) and
without (numpy / torch / scipy): the operator change of the damaged zone, the damage index,
the crack path and the pieces of the bond graph.

One realisation (``--seed``) is run and every ``--every``-th change is kept (the intact
fractions before and after, the active dofs, u at the factor and now); each piece is then
timed over those snapshots, best of ``--repeat`` passes, in ms per change.

    python benchmarks/fracture_changes.py [--side 100] [--seed 4] [--every 8] [--repeat 5]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from timing import best  # noqa: E402

from bayespd import bond_loops  # noqa: E402
from bayespd.damage import DamageIndex, crack_path  # noqa: E402
from bayespd.scenes.notched_plate import _unit_body, notched_plate  # noqa: E402
from bayespd.solvers import fracture  # noqa: E402
from bayespd.connectivity import CONNECTED  # noqa: E402

PARAMS = {"K": 2886.0, "s0": 0.0094}  # the posterior mean of experiments/crack_ensemble.py


def snapshots(scene, seed: int, every: int) -> list:
    """(intact at the factor, intact now, active dofs, u at the factor, u now) at every
    ``every``-th change of one run."""
    kept, updated = [], fracture.StochasticFracture._updated

    def keeping(self, base, intact, u, *rest):
        kept.append((base.intact.clone(), intact.clone(), base.active.copy(), base.u.clone(), u.clone()))
        return updated(self, base, intact, u, *rest)

    fracture.StochasticFracture._updated = keeping
    try:
        scene.build(PARAMS).run(scene.load_factors, scene.dt, seed=seed, hold=scene.hold,
                                path_threshold=scene.path_threshold, tangent=scene.tangent,
                                max_rank=scene.max_rank, zone=scene.zone)
    finally:
        fracture.StochasticFracture._updated = updated
    return kept[::every]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=float, default=100.0, help="plate side in mm (h = 1 mm): 100 -> 10k particles")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--every", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    if bond_loops.numba is None:
        raise SystemExit("numba is not installed: pip install -e '.[fast]' to compare the compiled loops")
    scene = notched_plate(side=args.side, h=1.0, steps=50, sigma=1500.0)
    body = _unit_body(args.side, 1.0, 3)
    kept = snapshots(scene, args.seed, args.every)
    index = DamageIndex(body.particles, body.bonds)
    phis = [index(after) for _, after, *_ in kept]
    changed = [int((after != before).sum()) for before, after, *_ in kept]
    print(f"load average {os.getloadavg()[0]:.2f}; {body.particles.n} particles, {body.n_bonds} bonds; seed "
          f"{args.seed}: {len(kept)} changes kept, {min(changed)}-{max(changed)} bonds changed since the factor; "
          f"up to {max(int((p > scene.path_threshold).sum()) for p in phis)} particles on the crack path")
    pieces = {
        "operator change": lambda: [body.operator_change(*k) for k in kept],
        "damage index": lambda: [index(after) for _, after, *_ in kept],
        "crack path": lambda: [crack_path(body.particles, phi, scene.path_threshold) for phi in phis],
        "pieces of the bond graph": lambda: [bond_loops.components(body.particles.n, body.bonds.i, body.bonds.j,
                                                                    after.numpy() > CONNECTED)
                                             for _, after, *_ in kept],
    }
    print(f"{'ms per change':>26} {'compiled':>9} {'without':>9}")
    for name, run in pieces.items():
        times = []
        for compiled in (True, False):
            bond_loops.ENABLED = compiled
            times.append(best(run, args.repeat) / len(kept) * 1e3)
        print(f"{name:>26} {times[0]:9.2f} {times[1]:9.2f}")


if __name__ == "__main__":
    main()
