"""The work–precision reading of `benchmarks/work_precision.py`: the front and the wall time
at an error (what issue #16's speed ratios are computed with)."""

import math
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import work_precision as wp  # noqa: E402


def _runs(pairs):
    return [dict(method="m", error=e, wall_s=w) for e, w in pairs]


def test_front_leaves_out_runs_beaten_in_error_and_time():
    # eG(3) on r3 (session 31): h = 1 and 0.714 are slower and less accurate than 0.625 and 0.5
    runs = _runs([(1.36e-4, 1.58), (1.10e-4, 1.10), (8.0e-5, 0.822), (6.4e-5, 0.811), (4.05e-5, 0.883),
                  (float("nan"), 0.1)])
    assert [(r["error"], r["wall_s"]) for r in wp.front(runs)] == [(6.4e-5, 0.811), (4.05e-5, 0.883)]


def test_wall_time_at_an_error_is_interpolated_on_the_front_only():
    # scipy Radau on r3: rtol 1e-3 took longer than 3e-4 for a larger error (dominated)
    radau = _runs([(2.38e-4, 35.6), (1.08e-4, 33.8), (4.3e-6, 34.9)])
    w = wp.interpolate_at(radau, 1e-4)
    s = (math.log(1e-4) - math.log(1.08e-4)) / (math.log(4.3e-6) - math.log(1.08e-4))
    assert w == pytest.approx(math.exp(math.log(33.8) + s * (math.log(34.9) - math.log(33.8))))
    assert wp.at_most(radau, 1e-4) is None
    # every front run more accurate than the target: no interpolation, the cheapest run bounds it
    eg = _runs([(1.36e-4, 1.58), (6.4e-5, 0.811), (4.05e-5, 0.883)])
    assert wp.interpolate_at(eg, 1e-4) is None
    assert wp.at_most(eg, 1e-4) == 0.811
    # every run less accurate: neither
    assert wp.interpolate_at(eg, 1e-6) is None and wp.at_most(eg, 1e-6) is None
