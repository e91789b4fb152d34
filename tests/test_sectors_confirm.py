"""Confirmation of "clear" over frames (companion.core.sectors_confirm, docs/derivations/sectors.md rule 11):
withheld until it has lasted, counted over the world's bearings as the vehicle turns, only ever clear → unknown."""

import dataclasses
import math

import numpy as np
import pytest

from companion.core.sectors import SectorConfig, SectorState, compute_sectors
from companion.core.sectors_confirm import confirm_clear
from companion.core.sectors_types import SECTOR_COUNT, UNKNOWN_CM
from companion.errors import ConfigError

HFOV = math.radians(60.0)
CFG = dataclasses.replace(SectorConfig(), clear_confirm_frames=3)


def hall(x=80.0, bearings_deg=np.arange(-28.0, 28.5, 0.5)):
    """Far points in the band over the camera's width: every sector fully in view is clear."""
    b = np.radians(bearings_deg)
    return np.stack([np.full(b.shape, x), x * np.tan(b), np.zeros(b.shape)], 1)


def sectors_of(points, config=CFG):
    p = np.asarray(points, float).reshape(-1, 3)
    n = len(p)
    return compute_sectors(p, np.full(n, 1.0), np.ones(n, bool), np.ones(n, bool), HFOV, 0.0, config)


def test_clear_is_withheld_until_it_has_lasted_and_a_gap_starts_the_count_again():
    s = sectors_of(hall())
    clear = s.state == SectorState.CLEAR
    assert clear[0] and clear.sum() >= 8 and s.forward.state == SectorState.CLEAR
    run = None
    for k in range(1, 4):
        out, run = confirm_clear(s, run, 0.0, CFG)
        assert np.all(run[clear] == k) and np.all(run[~clear] == 0)
        if k < 3:  # withheld: unknown, and the forward reading with it
            assert not np.any(out.state == SectorState.CLEAR) and np.all(out.distances_cm[clear] == UNKNOWN_CM)
            assert out.forward.state == SectorState.UNKNOWN and math.isnan(out.forward.distance_m)
        else:
            assert np.array_equal(out.distances_cm, s.distances_cm) and out.forward == s.forward
    unknown = sectors_of(np.zeros((0, 3)))  # a frame without evidence: every count back to 0
    out, run = confirm_clear(unknown, run, 0.0, CFG)
    assert not run.any() and out is unknown
    out, run = confirm_clear(s, run, 0.0, CFG)
    assert not np.any(out.state == SectorState.CLEAR)
    out, run = confirm_clear(s, run, math.nan, CFG)  # a yaw change not known: start afresh
    assert np.all(run[clear] == 1)


def test_one_frame_is_at_once_and_obstacles_are_never_touched():
    s = sectors_of(np.vstack([hall(), [[12.0, 0.0, 0.0]]]))
    assert s.state[0] == SectorState.OBSTACLE and s.forward.state == SectorState.OBSTACLE
    once = dataclasses.replace(CFG, clear_confirm_frames=1)
    out, run = confirm_clear(s, None, 0.0, once)
    assert out is s and np.all(run[s.state == SectorState.CLEAR] == 1)
    out, _ = confirm_clear(s, None, 0.0, CFG)
    assert out.state[0] == SectorState.OBSTACLE and out.distances_cm[0] == s.distances_cm[0] and out.forward == s.forward
    assert np.all(out.state[s.state != SectorState.CLEAR] == s.state[s.state != SectorState.CLEAR])


def test_the_count_follows_the_world_as_the_vehicle_turns():
    """Turned right by one sector, what was old sector i + 1 is new sector i; by half a sector a new sector
    overlaps two old ones and keeps the smaller count."""
    run_prev = np.zeros(SECTOR_COUNT, np.int64)
    run_prev[[1, 2, 3]] = [5, 2, 7]
    s = sectors_of(hall())
    clear = s.state == SectorState.CLEAR
    _, run = confirm_clear(s, run_prev, math.radians(5.0), CFG)
    assert run[0] == 6 and run[1] == 3 and run[2] == 8  # old 1, 2, 3 + this frame
    _, run = confirm_clear(s, run_prev, math.radians(7.5), CFG)  # between old i+1 and i+2
    assert run[0] == 3 and run[1] == 3 and run[2] == 1  # min(5, 2), min(2, 7), min(7, 0) + 1
    _, run = confirm_clear(s, run_prev, math.radians(-5.0), CFG)  # turned left
    assert run[2] == 6 and run[3] == 3 and run[4] == 8
    assert np.all(run[~clear] == 0)


def test_only_ever_withholds_clear_seeded():
    """Seeded Monte Carlo over random frame sequences and turns: a published sector differs from the frame's own
    only where that was clear and is now unknown, and a clear is published only after the configured run."""
    rng = np.random.default_rng(11)
    base = sectors_of(hall())
    for trial in range(40):
        cfg = dataclasses.replace(CFG, clear_confirm_frames=int(rng.integers(1, 5)))
        run = None
        for _ in range(12):
            keep = rng.random(SECTOR_COUNT) < 0.7
            state = np.where(keep, base.state, SectorState.UNKNOWN).astype(np.int8)
            dist = np.where(keep, base.distances_cm, UNKNOWN_CM).astype(np.uint16)
            s = dataclasses.replace(base, state=state, distances_cm=dist)
            turn = float(rng.choice([0.0, 2.0, 5.0, -7.5]))
            out, run = confirm_clear(s, run, math.radians(turn), cfg)
            changed = out.distances_cm != s.distances_cm
            assert np.all(s.state[changed] == SectorState.CLEAR) and np.all(out.state[changed] == SectorState.UNKNOWN)
            assert np.all(run[out.state == SectorState.CLEAR] >= cfg.clear_confirm_frames)


def test_the_setting_is_validated():
    with pytest.raises(ConfigError, match="clear_confirm_frames"):
        dataclasses.replace(SectorConfig(), clear_confirm_frames=0)
    with pytest.raises(ConfigError, match="clear_confirm_frames"):
        dataclasses.replace(SectorConfig(), clear_confirm_frames=2.0)
