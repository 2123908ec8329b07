"""The step's inverse Cholesky factors in one kernel (``Settings.cholesky = "kernel"``,
:mod:`softcrawl.jaxsim.factor`) against the library's factorisation and triangular solve, on
JAX's default device.

A robot's step inverts the factors of its legs' step matrices (``--legs`` per robot, 36 x 36 for
the shipped leg) and of its attachment block (72 x 72 for six legs). On random symmetric positive
definite matrices of those sizes and condition number ``--cond`` (the landed robots' leg step
matrices: about 1e5), float32, printed as JSON lines:

* ``"part": "agreement"``: each form's largest error against LAPACK's float64 factor inverted
  (numpy), relative to the factor's largest entry, per size; the kernel compiled for the GPU (or
  run in Pallas' interpreter where JAX has none);
* ``"part": "time"``: ``ms`` per call of each form at each of ``--robots`` (a call inverts every
  matrix of that many robots, each size in its own call), and on a GPU the kernel with other
  numbers of each matrix per thread (:data:`softcrawl.jaxsim.factor.PER_THREAD`, the warps).

Usage:
    python benchmarks/cholesky_kernel.py [--robots 96,16384] [--legs 6] [--cond 1e5] [--calls 20]
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", default="96,16384", help="robots per call at which the forms are timed")
    p.add_argument("--legs", type=int, default=6, help="leg step matrices per robot")
    p.add_argument("--sizes", default="36,72", help="the matrices' sizes: a leg's step matrix, the attachment block")
    p.add_argument("--cond", type=float, default=1e5)
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from softcrawl.jaxsim import factor

    device = jax.devices()[0]
    gpu = device.platform == "gpu"
    kernel = "kernel" if gpu else "interpret"
    head = {"device": f"{device.platform}:{device.device_kind}", "jax": jax.__version__, "cond": args.cond}
    rng = np.random.default_rng(args.seed)
    sizes = [int(n) for n in args.sizes.split(",")]

    def spd(batch, n):  # eigenvalues from 1 to cond, random eigenvectors
        Q, _ = np.linalg.qr(rng.standard_normal((batch, n, n)))
        return np.einsum("bij,j,bkj->bik", Q, np.geomspace(1.0, args.cond, n), Q)

    def batched(form):
        return jax.jit(jax.vmap(lambda a: factor.cholesky_inverse(a, form)))

    for n in sizes:
        A = spd(16, n)
        ref = np.linalg.inv(np.linalg.cholesky(A))
        err = {form: float(np.abs(np.asarray(batched(form)(jnp.asarray(A, jnp.float32)), float) - ref).max()
                           / np.abs(ref).max()) for form in ("library", kernel)}
        print(json.dumps({**head, "part": "agreement", "n": n, "kernel": kernel, "rel_error": err}), flush=True)
    default = factor.PER_THREAD
    for robots in (int(b) for b in args.robots.split(",")):
        out = {**head, "part": "time", "robots": robots}
        for n in sizes:
            count = robots * (args.legs if n == sizes[0] else 1)
            A = jnp.asarray(np.resize(spd(64, n), (count, n, n)), jnp.float32)

            def timed(f):
                jax.block_until_ready(f(A))
                t0 = time.perf_counter()
                for _ in range(args.calls):
                    r = f(A)
                jax.block_until_ready(r)
                return 1e3 * (time.perf_counter() - t0) / args.calls

            out[f"n{n}_matrices"] = count
            out[f"n{n}_library_ms"] = timed(batched("library"))
            if gpu:
                for per in dict.fromkeys((default, 8, 16, 32, 64)):
                    factor.PER_THREAD = per
                    jax.clear_caches()
                    out[f"n{n}_kernel_per_thread{per}_ms"] = timed(batched("kernel"))
                factor.PER_THREAD = default
                jax.clear_caches()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
