"""validation/twin/variant_benchmark.py: the comparison of two variants' renders, and a variant
that cannot run (no CUDA device on CI) reported with its error instead of stopping the run."""
from __future__ import annotations

import numpy as np
import pytest

from validation.twin import variant_benchmark as vb


def test_compare_reads_a_total_and_a_per_pixel_difference():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.5, 1.0, (40, 60, 3)).astype(np.float32)
    same = vb.compare(a, a.copy())
    assert same["total_ratio"] == 1.0 and same["median_rel_diff"] == 0.0 and same["pixels"] == 40 * 60
    brighter = vb.compare(a, a * 1.01)
    assert brighter["total_ratio"] == pytest.approx(1.01, rel=1e-6)
    assert brighter["median_rel_diff"] == pytest.approx(0.01, rel=1e-4)
    dark = a.copy()
    dark[:20] = 0.0                 # pixels without the sample's light are left out
    assert vb.compare(dark, dark)["pixels"] == 20 * 60


@pytest.mark.mitsuba
def test_a_variant_that_cannot_run_is_reported_not_raised(tmp_path):
    out = tmp_path / "variants.md"
    out.write_text("# title\n\nkept above the generated part\n\n" + vb.MEASURED + "\n\nold figures\n")
    assert vb.main(["--variants", "llvm_ad_rgb,no_such_variant", "--scales", "0.05", "--repeats", "1",
                    "--renders", str(tmp_path / "r"), "--out", str(out)]) == 0
    text = out.read_text()
    assert text.startswith("# title\n\nkept above the generated part\n\n" + vb.MEASURED) and "old figures" not in text
    assert "| llvm_ad_rgb | 0.05 | 302x202 |" in text
    assert "| no_such_variant | - |" in text and "did not run: " in text
    assert (tmp_path / "r" / "llvm_ad_rgb.npz").is_file()
