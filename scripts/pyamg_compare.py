#!/usr/bin/env python3
"""The core's multigrid against pyamg on the same planning problem (BENCHMARKS.md, solver issue).

For each world: build the discrete Laplace problem exactly as `harmonic-sim solve` does with
`--radius 0` (the vehicle's voxel at phi = 1, frontier voxels at phi = 0, walls zero-flux), solve
it with pyamg's smoothed aggregation + CG and with the core (`harmonic-sim solve`, which prints
its times as JSON and writes phi with `--out`), and compare both against a tight reference solve
(pyamg to a relative residual of 1e-12, float64).

Worlds: `--labels FILE --source X,Y,Z` for a grid of your own (uint8 .npy, 0 unknown, 1 free,
2 occupied, shape (NX, NY, NZ)), or generated houses (`--houses 64,96`): rooms off each other
through doors, a table and a cabinet per room, and one small window of unknown space in the far
room's outer wall, so only ~100 voxels are frontier, the case late in an exploration where
the solver issue found plain residual checks misleading. `--seed` moves doors and furniture; the
generator was not tuned against the solver.

Needs numpy, scipy and pyamg (`pip install pyamg`) and a release build of harmonic-sim:

    cargo build --release -p harmonic-sim
    python3 scripts/pyamg_compare.py --houses 64,96 --seeds 1,2

Prints one table row per world and solver: unknowns, frontier voxels, set-up and solve time (ms)
of the fastest of `--repeat` runs, the first run's total (ms), iterations, max |phi - reference|,
and the time ratio pyamg / core of the fastest runs. Both solvers repeat in one process (pyamg
in this one, the core in one `harmonic-sim solve --repeat` each), so only their first runs pay
for fresh memory.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import pyamg
import scipy.sparse as sp
from scipy import ndimage

UNKNOWN, FREE, OCCUPIED = 0, 1, 2


def house(n, seed):
    """A house on an n x n x (n // 2) grid: rooms n // 4 voxels across, doors, furniture, one
    unknown window. Returns (labels, source)."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = n, n, max(16, n // 2)
    g = np.full((nx, ny, nz), OCCUPIED, np.uint8)
    room = max(8, n // 4)
    ceiling = nz - 3
    g[1:nx - 1, 1:ny - 1, 1:ceiling] = FREE
    walls = list(range(room, nx - 2, room))
    door_h = min(ceiling - 1, 10)
    for w in walls:
        g[w, :, :] = OCCUPIED
        g[:, w, :] = OCCUPIED
    # Doors: one per wall segment between two rooms, 3 wide.
    edges = [0] + walls + [nx - 1]
    for w in walls:
        for a, b in zip(edges, edges[1:]):
            if b - a < 6:
                continue
            c = int(rng.integers(a + 2, b - 4))
            g[w, c:c + 3, 1:door_h] = FREE
            c = int(rng.integers(a + 2, b - 4))
            g[c:c + 3, w, 1:door_h] = FREE
    # Furniture: a table (slab on legs) and a cabinet in each room.
    for a, b in zip(edges, edges[1:]):
        for c, d in zip(edges, edges[1:]):
            if b - a < 8 or d - c < 8:
                continue
            tx, ty = int(rng.integers(a + 2, b - 6)), int(rng.integers(c + 2, d - 6))
            g[tx:tx + 4, ty:ty + 3, 7:8] = OCCUPIED
            for lx in (tx, tx + 3):
                for ly in (ty, ty + 2):
                    g[lx, ly, 1:7] = OCCUPIED
            cx, cy = int(rng.integers(a + 1, b - 3)), int(rng.integers(c + 1, d - 3))
            g[cx:cx + 2, cy:cy + 2, 1:min(ceiling, 16)] = OCCUPIED
    # The window: unknown space behind the far room's outer wall, 10 x 10 voxels open.
    y0, z0 = ny - room // 2 - 5, min(8, ceiling - 11)
    g[nx - 1, y0:y0 + 10, z0:z0 + 10] = UNKNOWN
    source = (room // 2, room // 2, min(6, ceiling - 2))
    g[source] = FREE
    return g, source


def domain(g, source):
    """The core's domain at radius 0: interior (free, no unknown face neighbour) connected to the
    source, the source itself, and the frontier voxels (free, an unknown face neighbour) next to
    them; the flood does not continue through frontier voxels."""
    unknown = g == UNKNOWN
    touches = np.zeros_like(unknown)
    for axis in range(3):
        for shift in (1, -1):
            moved = np.roll(unknown, shift, axis=axis)
            edge = [slice(None)] * 3
            edge[axis] = 0 if shift == 1 else -1
            moved[tuple(edge)] = False
            touches |= moved
    free = g == FREE
    calm = free & ~touches
    calm[source] = True
    comp, _ = ndimage.label(calm, structure=ndimage.generate_binary_structure(3, 1))
    inside = comp == comp[source]
    near = ndimage.binary_dilation(inside, structure=ndimage.generate_binary_structure(3, 1))
    frontier = free & touches & near & ~inside
    return inside, frontier


def system(g, source):
    """The Laplace rows of the interior unknowns: A phi = b with phi = 1 at the source and 0 at
    frontier voxels. Returns (A, b, index of each unknown, counts)."""
    inside, frontier = domain(g, source)
    interior = inside.copy()
    interior[source] = False
    ids = -np.ones(g.shape, np.int64)
    n = int(interior.sum())
    ids[interior] = np.arange(n)
    in_domain = inside | frontier
    diag = np.zeros(n)
    b = np.zeros(n)
    rows, cols = [], []
    coords = np.argwhere(interior)
    for axis in range(3):
        for step in (1, -1):
            nb = coords.copy()
            nb[:, axis] += step
            ok = (nb[:, axis] >= 0) & (nb[:, axis] < g.shape[axis])
            src = np.nonzero(ok)[0]
            t = tuple(nb[ok].T)
            dom = in_domain[t]
            diag[src[dom]] += 1
            j = ids[t]
            link = j >= 0
            rows.append(src[link])
            cols.append(j[link])
            is_source = np.all(nb[ok] == np.array(source), axis=1)
            b[src[is_source]] += 1.0
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    a = sp.csr_matrix((-np.ones(len(rows)), (rows, cols)), shape=(n, n)) + sp.diags(diag)
    return a.tocsr(), b, interior, int(frontier.sum())


def pyamg_solve(a, b, tol):
    t0 = time.perf_counter()
    ml = pyamg.smoothed_aggregation_solver(a, symmetry="symmetric")
    t1 = time.perf_counter()
    residuals = []
    x = ml.solve(b, tol=tol, accel="cg", residuals=residuals, maxiter=1000)
    t2 = time.perf_counter()
    return x, (t1 - t0) * 1e3, (t2 - t1) * 1e3, len(residuals) - 1


def core_solve(exe, labels_path, source, solver, tol, out, threads, repeat):
    # All runs in one process, as pyamg's are in this one: `solve --repeat` prints the fastest
    # run's times and the first run's total (which alone pays for fresh memory) as first_ms.
    cmd = [exe, "solve", "--labels", labels_path, "--source", ",".join(map(str, source)),
           "--solver", solver, "--tol", str(tol), "--radius", "0", "--out", out,
           "--threads", str(threads), "--repeat", str(repeat)]
    line = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip()
    return json.loads(line)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--labels", help="uint8 .npy grid (0 unknown, 1 free, 2 occupied)")
    p.add_argument("--source", help="X,Y,Z of the vehicle's voxel (with --labels)")
    p.add_argument("--houses", default="64,96", help="generated houses: sizes n (n x n x n/2)")
    p.add_argument("--seeds", default="1", help="generator seeds, comma-separated")
    p.add_argument("--tol", type=float, default=1e-6, help="relative residual for both solvers")
    p.add_argument("--exe", default="target/release/harmonic-sim")
    p.add_argument("--repeat", type=int, default=3,
                   help="runs per solver, all in one process each (the fastest is kept)")
    p.add_argument("--threads", type=int, default=2, choices=(1, 2),
                   help="the core's solver threads (pyamg runs on one)")
    args = p.parse_args()
    if not os.path.exists(args.exe):
        sys.exit(f"{args.exe} not found: cargo build --release -p harmonic-sim")

    worlds = []
    if args.labels:
        if not args.source:
            sys.exit("--labels needs --source X,Y,Z")
        worlds.append((args.labels, np.load(args.labels), tuple(int(v) for v in args.source.split(","))))
    else:
        for n in (int(v) for v in args.houses.split(",")):
            for seed in (int(v) for v in args.seeds.split(",")):
                g, src = house(n, seed)
                worlds.append((f"house {g.shape[0]}x{g.shape[1]}x{g.shape[2]} seed {seed}", g, src))

    print("| world | unknowns | frontier | solver | set-up ms | solve ms | first run ms | iterations | max error | pyamg / core |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, g, src in worlds:
            a, b, interior, frontier = system(g, src)
            exact = pyamg.smoothed_aggregation_solver(a, symmetry="symmetric").solve(
                b, tol=1e-12, accel="cg", maxiter=5000)
            runs = [pyamg_solve(a, b, args.tol) for _ in range(args.repeat)]
            x, setup, solve, its = min(runs, key=lambda r: r[1] + r[2])
            amg_ms = setup + solve
            first = runs[0][1] + runs[0][2]
            print(f"| {name} | {a.shape[0]} | {frontier} | pyamg SA + CG | {setup:.1f} | {solve:.1f} | "
                  f"{first:.1f} | {its} | {np.abs(x - exact).max():.1e} | |")
            path = os.path.join(tmp, "labels.npy")
            np.save(path, g)
            for solver in ("mg", "flat", "vc"):
                out = os.path.join(tmp, f"phi-{solver}.npy")
                r = core_solve(args.exe, path, src, solver, args.tol, out, args.threads, args.repeat)
                phi = np.load(out)[interior].astype(np.float64)
                if r["unknowns"] != a.shape[0]:
                    sys.exit(f"{name}: the core solved {r['unknowns']} unknowns, this script {a.shape[0]}")
                core_ms = r["setup_ms"] + r["solve_ms"]
                print(f"| {name} | {r['unknowns']} | {r['frontier']} | core {solver} | {r['setup_ms']:.1f} | "
                      f"{r['solve_ms']:.1f} | {r['first_ms']:.1f} | {r['cycles']} | "
                      f"{np.abs(phi - exact).max():.1e} | {amg_ms / core_ms:.1f}x |")


if __name__ == "__main__":
    main()
