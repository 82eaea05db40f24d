"""The exact bond force of every material law on an accelerator: agreement with the CPU and
time per evaluation, and explicit-dynamics steps per second (velocity Verlet, PMB).

The whole body is built under ``torch.device(DEVICE)`` (as ``ensemble.scene.realise_batch``
does), so every tensor of the material, the kinematics and the force lives there. For each law
(LPS, bond-based PMB, conical bond-based) and size: the relative difference of the force from
the CPU's (float64; the CPU value is taken only up to ``--check-max`` particles) and the
time of one force evaluation (float64 and float32, best of ``--repeat`` after a warm-up,
synchronised).

    python benchmarks/gpu_force.py [--device cuda] [--sizes 10000 160000 1000000] [--m 3]
"""
from __future__ import annotations

import argparse
import time

import torch

import bayespd as bp
from bayespd.solvers import lumped_mass, velocity_verlet

LAWS = {"lps": lambda p, b: bp.LPS(p, b), "pmb": lambda p, b: bp.BondBased(p, b),
        "conical": lambda p, b: bp.ConicalBondBased(p, b)}
MODULI = {"lps": {"K": 1.0, "G": 0.6}, "pmb": {"K": 1.0}, "conical": {"K": 1.0}}


def synchronised(device):
    return (lambda: torch.cuda.synchronize()) if device.type == "cuda" else (lambda: None)


def best(fn, repeat: int, sync) -> float:
    fn()
    sync()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return min(times)


def build(law: str, size: int, m: float, device):
    with torch.device(device):
        side = float(round(size ** 0.5))
        p = bp.grid_2d(side, side, 1.0)
        mat = LAWS[law](p, bp.find_bonds(p, m))
        kin = bp.NonlinearBonds(mat)
        u = torch.zeros(p.n, 2)
        u[:, 0] = 1e-4 * torch.as_tensor(p.x[:, 1])  # a shear: every bond loaded
        u[:, 1] = 1e-4 * torch.sin(torch.as_tensor(p.x[:, 0]))
    return p, mat, kin, u


def main():
    """Everything runs under ``torch.device(DEVICE)``, as ``ensemble.scene.realise_batch`` runs
    a realisation, so the tensors the force creates per call live there too."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 160_000, 1_000_000])
    parser.add_argument("--m", type=float, default=3.0)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--check-max", type=int, default=160_000)
    args = parser.parse_args()
    device = torch.device(args.device)
    with torch.device(device):
        run(args, device)


def run(args, device):
    sync = synchronised(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(f"device {name}, torch {torch.__version__}, m = {args.m:g}")
    print(f"{'law':>8} {'particles':>10} {'bonds':>10} {'rel diff CPU':>13} {'f64 ms':>8} {'f32 ms':>8}")
    for law in LAWS:
        for size in args.sizes:
            p, mat, kin, u = build(law, size, args.m, device)
            params = dict(MODULI[law], delta=args.m)
            forces = {dtype: kin.at(params, dtype) for dtype in (torch.float64, torch.float32)}
            f = forces[torch.float64].force(u)
            assert f.device.type == device.type, f"the force came back on {f.device}"
            diff = float("nan")
            if p.n <= args.check_max:
                with torch.device("cpu"):
                    _, _, kin_cpu, u_cpu = build(law, size, args.m, "cpu")
                    f_cpu = kin_cpu.at(params).force(u_cpu)
                diff = float((f.cpu() - f_cpu).norm() / f_cpu.norm())
            t64 = best(lambda: forces[torch.float64].force(u), args.repeat, sync)
            u32 = u.to(torch.float32)
            t32 = best(lambda: forces[torch.float32].force(u32), args.repeat, sync)
            print(f"{law:>8} {p.n:>10} {mat.bonds.n:>10} {diff:>13.2e} {1e3 * t64:>8.3f} {1e3 * t32:>8.3f}",
                  flush=True)
    print(f"\nvelocity Verlet, PMB, {args.steps} steps")
    for size in args.sizes:
        p, mat, kin, u = build("pmb", size, args.m, device)
        for dtype in (torch.float64, torch.float32):
            coef = kin.at({"K": 1.0, "delta": args.m}, dtype)
            M = lumped_mass(p, 1.0).to(device=device, dtype=dtype)
            v = u.to(dtype).reshape(-1)

            def force(w, coef=coef, shape=u.shape):
                return coef.force(w.view(shape)).view(-1)

            t = best(lambda: velocity_verlet(force, M, v, 0.05, args.steps), 2, sync) / args.steps
            print(f"  {p.n:>10} particles {str(dtype)[6:]:>8}: {1e3 * t:8.3f} ms/step "
                  f"{1e9 * t / p.n:8.2f} ns/particle-step", flush=True)


if __name__ == "__main__":
    main()
