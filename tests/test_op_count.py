"""The eager `fast` step stays within issue #16's 800 aten ops (`tools/count_ops.py`).

An op count, not a timing: deterministic for one torch build. Other torch versions may
decompose ops differently, so the bound is held for the version it was measured with.
"""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))
from count_ops import count_step_ops  # noqa: E402

MEASURED_WITH = "2.13."


@pytest.mark.skipif(not torch.__version__.startswith(MEASURED_WITH),
                    reason=f"op counts were measured with torch {MEASURED_WITH}x")
def test_a_fast_run_step_is_at_most_800_ops():
    # the batch size does not change the count; a small one keeps the test quick
    counts, phases = count_step_ops("fast", ["train.batch_size=256"], warm=2, run_setup=True,
                                    phases=True)
    total = sum(counts.values())
    assert total <= 800, f"a fast step dispatches {total} aten ops: {sorted(phases.items())}"
    # the hull's bounds are looked up in the pixel pool, not recomputed (99 ops before)
    assert phases["render/bounds"] <= 5, phases
