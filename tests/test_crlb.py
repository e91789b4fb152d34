"""Cramér–Rao bound (DESIGN §4): the brief's figures for seed 004, and an efficient estimator meets it."""

import numpy as np
import pytest

from bench.scenarios import Seed004Scenario
from companion.core.crlb import range_crlb
from companion.errors import InputError


def test_seed004_figures_from_the_brief():
    sc = Seed004Scenario()
    R, p = sc.true_poses()
    _, vis = sc.visibility(R, p)
    cam = sc.camera
    b = range_crlb(sc.points_world, R, p, vis, 2.0, cam.fx, cam.fy)[150]
    # DESIGN §4: about 2.1 m (|x| = 45), 2.5 m (|x| = 75), 6.2 m (|x| = 15) at σ = 2 px after 5 s
    assert b[1] == pytest.approx(2.1, abs=0.05) and b[4] == pytest.approx(2.1, abs=0.05)
    assert b[0] == pytest.approx(2.5, abs=0.1) and b[5] == pytest.approx(2.5, abs=0.1)
    assert b[2] == pytest.approx(6.2, abs=0.1) and b[3] == pytest.approx(6.2, abs=0.1)
    # the bound scales linearly with σ
    b4 = range_crlb(sc.points_world, R, p, vis, 4.0, cam.fx, cam.fy)[150]
    np.testing.assert_allclose(b4, 2 * b, rtol=1e-9)


def test_unobservable_is_infinite():
    p = np.array([[1.0, 0.0, 10.0]])
    R = np.broadcast_to(np.eye(3), (5, 3, 3))
    C = np.zeros((5, 3))  # no translation at all
    b = range_crlb(p, R, C, np.ones((5, 1), bool), 1.0, 500.0, 500.0)
    assert np.all(np.isinf(b))


def test_least_squares_monte_carlo_meets_the_bound():
    """Batch Gauss–Newton over all views is (asymptotically) efficient: its spread equals the bound."""
    f, sigma = 500.0, 1.0
    K = 20
    C = np.stack([np.linspace(0, 2, K), np.zeros(K), np.linspace(0, 6, K)], 1)
    R = np.broadcast_to(np.eye(3), (K, 3, 3))
    p = np.array([4.0, -1.0, 30.0])
    bound = range_crlb(p[None], R, C, np.ones((K, 1), bool), sigma, f, f)[-1, 0]
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(400):
        uv = f * (p - C)[:, :2] / (p - C)[:, 2:3] + sigma * rng.standard_normal((K, 2))
        x = p + rng.normal(scale=1.0, size=3)
        for _ in range(10):
            d = x - C
            r = (uv - f * d[:, :2] / d[:, 2:3]).reshape(-1)
            J = np.zeros((K, 2, 3))
            J[:, 0, 0] = f / d[:, 2]
            J[:, 0, 2] = -f * d[:, 0] / d[:, 2] ** 2
            J[:, 1, 1] = f / d[:, 2]
            J[:, 1, 2] = -f * d[:, 1] / d[:, 2] ** 2
            J = J.reshape(-1, 3)
            x = x + np.linalg.lstsq(J, r, rcond=None)[0]
        errs.append(np.linalg.norm(x - C[-1]) - np.linalg.norm(p - C[-1]))
    assert np.std(errs) == pytest.approx(bound, rel=0.12)


def test_shapes_checked():
    with pytest.raises(InputError, match="visible"):
        range_crlb(np.zeros((2, 3)), np.broadcast_to(np.eye(3), (4, 3, 3)), np.zeros((4, 3)), np.ones((4, 3), bool), 1.0, 1.0, 1.0)
