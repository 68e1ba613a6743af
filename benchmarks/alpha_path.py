"""The ``fit/alpha_path`` row alone, at 1264 actuators x 12 taps (its cost does not depend on the frames):

    .venv/bin/python -m benchmarks.alpha_path

Prints the path's and the single solve's times (min and median over repeats) and their ratio, twice.
"""

from __future__ import annotations

from benchmarks.bench_fit import alpha_path_row, synthetic_regression
from benchmarks.common import synchronizer


def main() -> None:
    x, t = synthetic_regression(1264, 5000, 12)
    for _ in range(2):
        row = alpha_path_row(x, t, 7, 1e-9, "cpu", synchronizer("cpu"))
        print(f"path {row.eofnn.min * 1e3:.1f} ms (median {row.eofnn.median * 1e3:.1f}), one solve "
              f"{row.baseline.min * 1e3:.1f} ms (median {row.baseline.median * 1e3:.1f}): ratio "
              f"{row.baseline.min / row.eofnn.min:.2f} (medians {row.baseline.median / row.eofnn.median:.2f}); "
              f"weights agree to {row.info['max_relative_weight_difference']:.1e}")


if __name__ == "__main__":
    main()
