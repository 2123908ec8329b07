"""Robot contact solves per second of :mod:`softcrawl.jaxsim.contact`, batched over robots,
on whatever device JAX has (CPU or GPU).

For each precision, solver and batch size it builds ``batch`` random robots' constraint
problems on the device (``--bilateral`` attachment rows and ``--contacts`` contact blocks;
``W = J J^T / 60 + 0.05 I`` with ``J`` ``(rows, 60)`` standard normal: a rank-60 body plus
regularisation, as the Gauss-Seidel probe measured before; ``q`` standard normal; mu 1.2;
a fraction ``--padding`` of the contact blocks inactive), solves them with
``jax.jit(jax.vmap(solve_constraints))`` for a fixed ``--sweeps`` (Gauss-Seidel sweeps or
accelerated-gradient iterations) from a zero warm start, and prints one JSON line: robot
solves/s (best of ``--repeats`` timed calls after one compiling call), compile time, the
median and worst natural-map residual relative to the largest impulse (how converged the
fixed sweep count leaves the batch), device, peak memory (device bytes where JAX reports
them, else the process's peak resident set).

Usage: python benchmarks/gpu_contact.py [--contacts 40] [--sweeps 100] [--bilateral 0]
       [--batches 1 16 64 256 1024 4096 16384] [--max-batch N] [--dtypes float32 float64]
       [--methods pgs apgd] [--padding 0.25] [--repeats 3]
``--max-batch`` caps the batch sizes (default: 256 on a CPU, none on an accelerator).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)  # float64 runs need it; float32 arrays stay float32

from softcrawl.jaxsim.contact import solve_constraints  # noqa: E402


def problems(key, batch: int, nb: int, k: int, padding: float, dtype):
    """``(W, q, bilateral, mu, lam0, active)`` of ``batch`` random robots on the device (module doc)."""
    n = nb + 3 * k
    kj, kq, ka = jax.random.split(key, 3)
    J = jax.random.normal(kj, (batch, n, 60), dtype)
    W = J @ jnp.swapaxes(J, 1, 2) / 60 + 0.05 * jnp.eye(n, dtype=dtype)
    q = jax.random.normal(kq, (batch, n), dtype)
    active = jax.random.uniform(ka, (batch, k)) >= padding
    return (W, q, jnp.ones((batch, nb), bool), jnp.full((batch, k), 1.2, dtype), jnp.zeros((batch, 3 * k), dtype),
            active)


def peak_memory() -> dict:
    """Peak device bytes where JAX reports them, and the process's peak resident set (bytes)."""
    stats = jax.devices()[0].memory_stats() or {}
    out = {"peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
    if "peak_bytes_in_use" in stats:
        out["device_peak_bytes"] = int(stats["peak_bytes_in_use"])
    return out


def run(args, dtype_name: str, method: str, batch: int) -> dict:
    dtype = jnp.dtype(dtype_name)
    data = problems(jax.random.PRNGKey(batch), batch, args.bilateral, args.contacts, args.padding, dtype)
    jax.block_until_ready(data)
    solve = jax.jit(jax.vmap(lambda *a: solve_constraints(*a, args.sweeps, method=method, return_residuals=True)))
    t0 = time.perf_counter()
    lam, res = jax.block_until_ready(solve(*data))
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(solve(*data))
        best = min(best, time.perf_counter() - t0)
    scale = np.maximum(np.abs(np.asarray(lam, np.float64)).max(axis=1), 1e-300)
    rel = np.asarray(res["natural_map"], np.float64) / scale
    return {"method": method, "dtype": dtype_name, "robots": batch, "contacts": args.contacts,
            "bilateral_rows": args.bilateral, "sweeps": args.sweeps, "padding": args.padding,
            "robot_solves_per_s": batch / best, "solve_ms": best * 1e3, "compile_s": compile_s,
            "natural_map_rel_median": float(np.median(rel)), "natural_map_rel_max": float(rel.max()),
            "device": str(jax.devices()[0]), "platform": platform.processor() or platform.machine(),
            **peak_memory()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--contacts", type=int, default=40)
    p.add_argument("--sweeps", type=int, default=100)
    p.add_argument("--bilateral", type=int, default=0, help="attachment rows per robot (3 per attachment)")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64, 256, 1024, 4096, 16384])
    p.add_argument("--max-batch", type=int, default=None)
    p.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    p.add_argument("--methods", nargs="+", default=["pgs", "apgd"], choices=["pgs", "apgd"])
    p.add_argument("--padding", type=float, default=0.25, help="fraction of inactive contact blocks")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    cap = args.max_batch if args.max_batch is not None else (256 if jax.devices()[0].platform == "cpu" else None)
    for dtype in args.dtypes:
        for method in args.methods:
            for batch in args.batches:
                if cap is None or batch <= cap:
                    print(json.dumps(run(args, dtype, method, batch)), flush=True)


if __name__ == "__main__":
    main()
