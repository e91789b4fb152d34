"""The seed-004 benchmark's options (bench/seed004.py): the anchored EKF's iterations reach the filter."""

import dataclasses
import subprocess
import sys

import numpy as np

from bench import seed004
from bench.scenarios import Seed004Scenario


def test_ekf_iterations_reach_the_anchored_filter():
    sc = Seed004Scenario()
    assert seed004.filter_configs(2.0, False, sc)[0].iterations == 2  # the published tables' setting
    assert seed004.filter_configs(2.0, False, sc, ekf_iterations=1)[0].iterations == 1
    case = seed004.CaseSpec(4.0, False)
    plain = seed004.run_once(7, dataclasses.replace(case, ekf_iterations=1), sc)
    iterated = seed004.run_once(7, case, sc)
    # same noise draw, other update: the anchored filter's errors differ, the landmark filter's do not
    a, b = plain["err"]["ekf_anchored"][-1], iterated["err"]["ekf_anchored"][-1]
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and not np.allclose(a, b)
    assert np.array_equal(plain["err"]["ekf_landmark"], iterated["err"]["ekf_landmark"], equal_nan=True)
    assert np.all(np.isfinite(plain["nees"])) and len(plain["nees"]) == 6


def test_ekf_iterations_option_is_checked():
    r = subprocess.run([sys.executable, "-m", "bench", "seed004", "--runs", "1", "--ekf-iterations", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "--ekf-iterations" in r.stderr
