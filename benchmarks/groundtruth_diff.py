"""Two ground truths of one design set compared design by design (e.g. the same search with other
seeds, ``softcrawl groundtruth --seeds``), as JSON.

For the designs both hold (a finished and a partial folder compare on the finished part): how
many gained or lost more than ``--tol`` (in the task's unit), the largest gain and loss, the
Spearman rank correlation of their rewards, each one's top ``--top`` designs, and for every
design given with ``--design`` its reward and rank in each (ranks among the shared designs,
1 = best; ties share the better rank).

Usage: python benchmarks/groundtruth_diff.py OLD NEW [--tol 0.5] [--top 10] [--design 0,0,0,1,1,1,0,0 ...]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from softcrawl.codesign.groundtruth import load_results, spearman
from softcrawl.codesign.groundtruth.store import folder_space


def ranks(rewards: np.ndarray) -> np.ndarray:
    """``(n,)`` rank of each reward among ``rewards`` (1 = best; ties share the better rank)."""
    return 1 + np.array([int(np.sum(rewards > r)) for r in rewards])


def compare(old: str, new: str, tol: float, top: int, designs: list[str]) -> dict:
    """The comparison of the module docstring.

    Raises:
        ValueError: the folders share no finished design, or a ``designs`` entry is not a design
            of the space or not in both.
    """
    a, b = load_results(old), load_results(new)
    shared = sorted(set(a) & set(b))
    if not shared:
        raise ValueError(f"{old} and {new} share no finished design")
    ra = np.array([a[d].reward_cm for d in shared])
    rb = np.array([b[d].reward_cm for d in shared])
    rank_a, rank_b = ranks(ra), ranks(rb)
    delta = rb - ra

    def name(d) -> str:
        return ",".join(map(str, d))

    def best(rewards: np.ndarray) -> list:
        return [[name(shared[i]), round(float(rewards[i]), 3)] for i in np.argsort(-rewards, kind="stable")[:top]]

    space = folder_space(new)
    asked = {}
    for text in designs:
        d = space.canonicalize(tuple(int(v) for v in text.split(",")))
        if d not in a or d not in b:
            raise ValueError(f"design {name(d)} is not finished in both ground truths")
        i = shared.index(d)
        asked[name(d)] = {"old": round(float(ra[i]), 3), "new": round(float(rb[i]), 3),
                          "old_rank": int(rank_a[i]), "new_rank": int(rank_b[i])}
    return {"old": str(old), "new": str(new), "shared": len(shared), "tol": tol,
            "gained": int(np.sum(delta > tol)), "lost": int(np.sum(delta < -tol)),
            "largest_gain": [name(shared[int(np.argmax(delta))]), round(float(delta.max()), 3)],
            "largest_loss": [name(shared[int(np.argmin(delta))]), round(float(delta.min()), 3)],
            "spearman": round(spearman(ra, rb), 4) if len(shared) > 1 else None,
            "top_old": best(ra), "top_new": best(rb), "designs": asked}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--tol", type=float, default=0.5, help="a change smaller than this is none (the task's unit)")
    p.add_argument("--top", type=int, default=10)
    p.add_argument("--design", action="append", default=[], help="a design to place in both (repeatable)")
    args = p.parse_args()
    print(json.dumps(compare(args.old, args.new, args.tol, args.top, args.design), indent=1))


if __name__ == "__main__":
    main()
