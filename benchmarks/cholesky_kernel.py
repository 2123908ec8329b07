"""The step's inverses in one kernel each (``Settings.cholesky = "kernel"``,
:mod:`softcrawl.jaxsim.factor`) against the library's factorisation and triangular solve, on
JAX's default device.

A robot's step inverts the Cholesky factors of its legs' step matrices (``--legs`` per robot, 36
x 36 for the shipped leg; ``cholesky_inverse``, by elimination in the kernel) and its attachment
block (72 x 72 for six legs; ``inverse_spd``, by sweeps in the kernel). Each function in each
form, on random symmetric positive definite matrices of both sizes and condition number
``--cond`` (the landed robots' leg step matrices: about 1e5), float32, printed as JSON lines:

* ``"part": "agreement"``: each form's largest error against numpy's float64 result (the factor
  inverted, or the inverse), relative to its largest entry, per function and size; the kernel
  compiled for the GPU (or run in Pallas' interpreter where JAX has none);
* ``"part": "step"``: each leg's step matrix formed, factored and its free motion solved
  (``step_solve``, the step's form of the legs' factor) in one kernel program a leg
  (``step_in_kernel_ms``) and with XLA forming the matrix and multiplying by the factor around
  ``cholesky_inverse``'s kernel (``step_split_ms``; :data:`softcrawl.jaxsim.factor.STEP_IN_KERNEL`
  off), ``ms`` per call at each of ``--robots`` on a GPU, and ``max_rel_difference``, the two
  forms' largest difference relative to the largest change of ``x`` (interpreted on a CPU: 8
  legs, no times);
* ``"part": "time"``: ``ms`` per call of each function and form at each of ``--robots`` (a call
  treats every matrix of that many robots, each size in its own call), and on a GPU the kernels
  with other numbers of each matrix per thread (:data:`softcrawl.jaxsim.factor.PER_THREAD`, the
  warps), and with the pivots unrolled or looped, whichever is not the default, at 64 and 128
  (:data:`~softcrawl.jaxsim.factor.UNROLL_PIVOTS`; ``_unrolled`` in the key). The inverse's
  kernel is timed at every batch size, whatever :data:`~softcrawl.jaxsim.factor.LIBRARY_FROM`
  (the batch from which its form would hand the matrices to the library): the sizes between 96
  and 16,384 robots say whether the library is faster anywhere.

Usage:
    python benchmarks/cholesky_kernel.py [--robots 96,1024,2048,4096,16384] [--legs 6] [--cond 1e5] [--calls 20]
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", default="96,1024,2048,4096,16384", help="robots per call at which the forms are timed")
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

    functions = {"factor": factor.cholesky_inverse, "inverse": factor.inverse_spd}

    def batched(function, form):
        return jax.jit(jax.vmap(lambda a: functions[function](a, form)))

    for n in sizes:
        A = spd(16, n)
        refs = {"factor": np.linalg.inv(np.linalg.cholesky(A)), "inverse": np.linalg.inv(A)}
        for function, ref in refs.items():
            got = {form: np.asarray(batched(function, form)(jnp.asarray(A, jnp.float32)), float)
                   for form in ("library", kernel)}
            err = {form: float(np.abs(g - ref).max() / np.abs(ref).max()) for form, g in got.items()}
            print(json.dumps({**head, "part": "agreement", "function": function, "n": n, "kernel": kernel,
                              "rel_error": err}), flush=True)
    if sizes[0] > 3:  # a leg's step: its stiffness on all but three modes (the rigid ones), as the shipped leg's
        n = sizes[0]
        M, slots = jnp.asarray(spd(1, n)[0] / args.cond, jnp.float32), jnp.asarray(np.r_[[n - 3] * 3, :n - 3])
        for robots in (int(b) for b in args.robots.split(",")):
            count = robots * args.legs if gpu else 8  # interpreted: a few legs, for the agreement
            K, f_s, f, x = (jnp.asarray(a, jnp.float32) for a in (np.resize(spd(64, n - 3), (count, n - 3, n - 3)),
                                                                    rng.standard_normal((count, n - 3)),
                                                                    rng.standard_normal((count, n)),
                                                                    rng.standard_normal((count, n))))
            out = {**head, "part": "step", "robots": robots, "legs": count}
            ends = []
            for in_kernel in (True, False):
                factor.STEP_IN_KERNEL = in_kernel
                jax.clear_caches()
                step = jax.jit(jax.vmap(lambda *a: factor.step_solve(M, a[0], a[1], slots, a[2], True, a[3], 1.0, 1.0,
                                                                     0.01, 0.1, kernel)))
                ends.append(np.asarray(jax.block_until_ready(step(K, f_s, f, x))[1], float))
                if gpu:
                    t0 = time.perf_counter()
                    for _ in range(args.calls):
                        r = step(K, f_s, f, x)
                    jax.block_until_ready(r)
                    ms = 1e3 * (time.perf_counter() - t0) / args.calls
                    out[f"step_{'in_kernel' if in_kernel else 'split'}_ms"] = ms
            factor.STEP_IN_KERNEL = True
            jax.clear_caches()
            out["max_rel_difference"] = float(np.abs(ends[0] - ends[1]).max() / np.abs(ends[1] - np.asarray(x)).max())
            print(json.dumps(out), flush=True)
            if not gpu:
                break  # interpreted: the agreement once
    default, unrolled = factor.PER_THREAD, factor.UNROLL_PIVOTS
    factor.LIBRARY_FROM = 1 << 62  # the kernel at every batch size (a number: older trees on PYTHONPATH compare it)
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
            for function in functions:
                out[f"n{n}_{function}_library_ms"] = timed(batched(function, "library"))
                if gpu:
                    for unroll in dict.fromkeys((unrolled, max(sizes) * (not unrolled))):
                        for per in dict.fromkeys((default, 16, 32, 64, 128) if unroll == unrolled else (64, 128)):
                            factor.PER_THREAD, factor.UNROLL_PIVOTS = per, unroll
                            jax.clear_caches()
                            name = f"n{n}_{function}_kernel_per_thread{per}{'_unrolled' * (n <= unroll)}_ms"
                            if name not in out:
                                out[name] = timed(batched(function, "kernel"))
                    factor.PER_THREAD, factor.UNROLL_PIVOTS = default, unrolled
                    jax.clear_caches()
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
