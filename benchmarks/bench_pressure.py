"""Pressure projection: warpsim's matrix-free Poisson solve (``warp.optim.linear.cg``, float32) with
its Jacobi, red-black symmetric Gauss-Seidel and multigrid preconditioners against each other and
against SciPy's sparse CG (float64, Jacobi preconditioner) on the same Poisson system, in one process.

The system: a smoke domain (every non-solid cell fluid) with a solid sphere and an open top,
right-hand side the divergence of a random smooth velocity. The matrix SciPy solves is read out
of warpsim's own coefficients and checked against the operator on a random vector; both solvers
stop at the same relative residual. Printed per preconditioner: iterations (both CG passes), seconds per
solve (Warp: the whole projection, with coefficient assembly, divergence and gradient subtraction;
SciPy: CG only), seconds per iteration, the speed-up over the first preconditioner, the ratio
SciPy / Warp and the relative difference of the Warp and SciPy pressures.

    python benchmarks/bench_pressure.py                        # 32^3 and 64^3 on the CPU
    python benchmarks/bench_pressure.py --sizes 128 256 --device cuda:0
    python benchmarks/bench_pressure.py --sizes 64 --preconditioners jacobi mg
"""

import argparse
import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.grid_fluids.mac_grid import MacGrid
from warpsim.grid_fluids.pressure import PressureSolver


def make_grid(n, device):
    g = MacGrid((n, n, n), 1.0 / n, open_sides=("+y",), device=device)
    g.add_sphere((0.5, 0.4, 0.5), 0.2)
    return g


def set_velocity(g, seed=0):
    rng = np.random.default_rng(seed)
    k = rng.uniform(2.0, 6.0, (3, 3))
    g.set_velocity(lambda p: np.stack([np.sin(p @ k[a]) for a in range(3)], -1))


def scipy_matrix(solver):
    """The operator as a SciPy CSR matrix, from the solver's coefficient arrays."""
    shape = solver.grid.shape
    n = solver.grid.cell_count
    idx = np.arange(n).reshape(shape)
    diag = solver.diag.numpy().reshape(-1)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], [diag]
    for axis, plus in enumerate(solver.plus):
        p = plus.numpy()
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        a, b, v = idx[tuple(lo)].ravel(), idx[tuple(hi)].ravel(), p[tuple(lo)].ravel()
        keep = v != 0.0
        rows += [a[keep], b[keep]]
        cols += [b[keep], a[keep]]
        vals += [v[keep], v[keep]]
    return sp.csr_matrix((np.concatenate(vals).astype(np.float64), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n, n))


def time_projection(g, preconditioner, tol, repeats, device):
    """Best wall time of ``repeats`` projections (after a warm-up), the last iteration count and solver."""
    solver = PressureSolver(g, tol=tol, preconditioner=preconditioner)
    set_velocity(g)
    solver.project()  # compile, warm up
    times = []
    for r in range(repeats):
        set_velocity(g, r)
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        iterations = solver.project()
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return min(times), iterations, solver


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--device", default=None)
    parser.add_argument("--tol", type=float, default=1e-5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--preconditioners", nargs="+", default=["jacobi", "rbgs", "mg"],
                        choices=["jacobi", "rbgs", "mg"])
    args = parser.parse_args()
    device = wp.get_device(device_arg(args.device))
    print(f"device {device}, tol {args.tol:g}; ratios against the first preconditioner "
          f"({args.preconditioners[0]}) and against SciPy CG (float64, Jacobi)")
    print(f"{'cells':>10} {'precond':>8} {'warp it':>8} {'warp s':>9} {'s/it':>9} {'speedup':>8} "
          f"{'scipy it':>9} {'scipy s':>9} {'scipy/warp':>11} {'|dq|/|q|':>9}")
    for n in args.sizes:
        g = make_grid(n, device)
        rows = [(pc, *time_projection(g, pc, args.tol, args.repeats, device)) for pc in args.preconditioners]
        solver = rows[0][3]
        # SciPy on the same system (the last repeat's right-hand side, the same for every preconditioner)
        A = scipy_matrix(solver)
        x = np.random.default_rng(5).standard_normal(A.shape[0])
        ax = wp.zeros(A.shape[0], dtype=float, device=device)
        solver.apply(wp.array(x.astype(np.float32), dtype=float, device=device), ax)
        assert np.allclose(ax.numpy(), A @ x, rtol=1e-4, atol=1e-4), "SciPy matrix differs from the Warp operator"
        b = solver.rhs.numpy().astype(np.float64)
        M = sp.diags(1.0 / A.diagonal())
        count = [0]

        def callback(_xk, count=count):
            count[0] += 1

        t0 = time.perf_counter()
        q_scipy, info = spla.cg(A, b, rtol=args.tol, atol=0.0, M=M, maxiter=10 * solver.max_iterations,
                                callback=callback)
        t_scipy = time.perf_counter() - t0
        t_ref = rows[0][1]
        for pc, t_warp, iterations, s in rows:
            diff = np.linalg.norm(q_scipy - s.q.numpy()) / np.linalg.norm(q_scipy)
            print(f"{g.cell_count:>10} {pc:>8} {iterations:>8} {t_warp:>9.4f} {t_warp / max(iterations, 1):>9.2e} "
                  f"{t_ref / t_warp:>8.2f} {count[0]:>9} {t_scipy:>9.4f} {t_scipy / t_warp:>11.2f} {diff:>9.1e}"
                  + ("" if info == 0 else f"  (scipy info {info})"))


if __name__ == "__main__":
    sys.exit(run_script(main))
