"""A reduction file's metadata is checksummed and checked against its arrays on load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest


def _shipped():
    import softcrawl.reduction.data as data

    return Path(data.__file__).parent / "pneunet_6mm.npz"


def _rewrite(path: Path, edit) -> None:
    with np.load(_shipped(), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("metadata").tobytes().decode())
    meta = edit(meta, arrays)
    np.savez(path, metadata=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def test_reduction_metadata_is_covered_and_checked(tmp_path):
    from softcrawl.reduction.artifact import ReductionFileError, _checksum, _metadata_checksum, load_reduction

    def heavier(meta, arrays):
        meta["valid_for"]["leg_mass"] = 1.0  # the reduction would then load for another model
        return meta

    _rewrite(tmp_path / "a.npz", heavier)
    with pytest.raises(ReductionFileError, match="metadata"):
        load_reduction(tmp_path / "a.npz")

    def rigid(meta, arrays):
        arrays["leg__n_rigid"] = np.array(40)
        meta["parts"]["leg"]["n_rigid"] = 40
        meta["checksum"] = _checksum(arrays)
        meta["metadata_checksum"] = _metadata_checksum(meta)
        return meta

    _rewrite(tmp_path / "b.npz", rigid)
    with pytest.raises(ReductionFileError, match="n_rigid"):
        load_reduction(tmp_path / "b.npz")
    _rewrite(tmp_path / "c.npz", lambda meta, arrays: [meta])
    with pytest.raises(ReductionFileError, match="not a JSON object"):
        load_reduction(tmp_path / "c.npz")
    with pytest.raises(ReductionFileError, match="directory"):
        load_reduction(tmp_path)
    load_reduction(_shipped())  # the shipped file stays valid
