"""The legs' RID product of the ``pairs`` form (:func:`softcrawl.jaxsim.legs.rid_terms`) at each
float32 dot algorithm JAX offers on the device: time and error against float64.

The product is ``mono (legs, M' E) @ S (M' E, m'(m'+1)/2)`` (each element's frame monomials and its
stiffness per monomial, :func:`softcrawl.jaxsim.legs.frame_stiffness`) with the shipped leg's sizes
(11,595 by 561; random data of the same scale), for the legs of ``--robots`` six-legged robots. Prints one JSON
line per algorithm: ``ms`` (median of ``--calls``), ``rel_error`` (``|out - ref| / |ref|``, Frobenius,
against a float64 product on the host) and ``tflops``.

    python benchmarks/dot_algorithms.py [--robots 96] [--calls 20]
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=96)
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--inner", type=int, default=11595, help="M' E, the products' inner size")
    p.add_argument("--cols", type=int, default=561, help="m'(m'+1)/2")
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    rng = np.random.default_rng(0)
    legs = 6 * args.robots
    G = rng.standard_normal((legs, args.inner)).astype(np.float32)
    T = rng.standard_normal((args.inner, args.cols)).astype(np.float32)
    ref = G.astype(np.float64) @ T.astype(np.float64)
    g, t = jnp.asarray(G), jnp.asarray(T)
    device = jax.devices()[0]
    for name in ("F32_F32_F32", "TF32_TF32_F32_X3", "BF16_BF16_F32_X6", "BF16_BF16_F32_X3", "TF32_TF32_F32"):
        algo = getattr(jax.lax.DotAlgorithmPreset, name)
        f = jax.jit(lambda a, b, algo=algo: jnp.matmul(a, b, precision=algo))
        try:
            out = np.asarray(jax.block_until_ready(f(g, t)), np.float64)
        except Exception as e:  # an algorithm the device lacks
            print(json.dumps({"algorithm": name, "error": str(e).splitlines()[0][:200]}), flush=True)
            continue
        times = []
        for _ in range(args.calls):
            t0 = time.perf_counter()
            jax.block_until_ready(f(g, t))
            times.append(time.perf_counter() - t0)
        ms = 1e3 * float(np.median(times))
        print(json.dumps({"algorithm": name, "device": f"{device.platform}:{device.device_kind}", "legs": legs,
                          "ms": ms, "tflops": 2 * legs * args.inner * args.cols / ms / 1e9,
                          "rel_error": float(np.linalg.norm(out - ref) / np.linalg.norm(ref))}), flush=True)


if __name__ == "__main__":
    main()
