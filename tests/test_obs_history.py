"""Per-landmark observation histories for the batch refinement (companion/core/obs_history.py): slots in time order,
looming linked to the previous frame, incomplete histories, the due schedule, bounded memory."""

import numpy as np
import pytest

from companion.core.obs_history import ObservationHistory
from companion.errors import InputError

I3 = np.eye(3)


def _C(t):
    return np.array([0.0, 0.0, t])


def test_slots_hold_pose_pixel_and_looming_in_time_order():
    h = ObservationHistory(16)
    h.record_anchor([5, 3], 0.0, I3, _C(0.0))
    h.record_pixels([3, 5], 0.1, I3, _C(0.1), [[0.1, 0.2], [0.3, 0.4]])
    h.record_looming([5], 0.1, I3, _C(0.1), 0.0, [1.01], [1e-4])  # attaches to frame 0.1's slot
    h.record_looming([3], 0.2, I3, _C(0.2), 0.1, [1.02], [2e-4])  # its pixel refused at 0.2: a slot of its own
    cnt, complete = h.counts([3, 5, 9])
    assert cnt.tolist() == [3, 2, 0] and complete.tolist() == [True, True, False]
    g = h.gather([5, 3])
    assert g["owner"].tolist() == [0, 0, 1, 1, 1] and g["starts"].tolist() == [0, 2] and g["counts"].tolist() == [2, 3]
    assert g["prev"].tolist() == [-1, 0, -1, 2, 3]
    assert np.allclose(g["t"], [0.0, 0.1, 0.0, 0.1, 0.2])
    assert np.isnan(g["z"][0]).all() and np.allclose(g["z"][1], [0.3, 0.4]) and np.isnan(g["z"][4]).all()
    assert np.isnan(g["s"][[0, 2, 3]]).all() and np.allclose(g["s"][[1, 4]], [1.01, 1.02])
    assert np.allclose(g["s_var"][[1, 4]], [1e-4, 2e-4]) and np.allclose(g["C"][4], [0, 0, 0.2])
    with pytest.raises(InputError, match="unknown"):
        h.gather([9])


def test_looming_without_the_previous_frame_marks_the_history_incomplete():
    h = ObservationHistory(16)
    h.record_anchor([1, 2], 0.0, I3, _C(0.0))
    h.record_pixels([1, 2], 0.1, I3, _C(0.1), [[0, 0], [0, 0]])
    # frame 0.2: landmark 1's pixel and looming both refused; at 0.3 its looming relates 0.3 to 0.2, which it lacks
    h.record_pixels([2], 0.2, I3, _C(0.2), [[0, 0]])
    h.record_looming([1, 2], 0.3, I3, _C(0.3), 0.2, [1.0, 1.0], [1e-4, 1e-4])
    cnt, complete = h.counts([1, 2])
    assert complete.tolist() == [False, True] and cnt.tolist() == [2, 4]
    h.record_pixels([1], 0.4, I3, _C(0.4), [[0, 0]])  # an incomplete history records nothing more
    assert h.counts([1])[0].tolist() == [2] and not h.due([1])[0]


def test_due_schedule_doubles_up_to_the_capacity_then_seals():
    h = ObservationHistory(40, first_due=8)
    due_at = []
    h.record_anchor([1], 0.0, I3, _C(0.0))
    for k in range(1, 60):
        h.record_pixels([1], k / 30, I3, _C(k / 30), [[0, 0]])
        if h.due([1])[0]:
            due_at.append(int(h.counts([1])[0][0]))
            h.advance([1])
    assert due_at == [8, 16, 32, 40]
    # sealed: nothing held, nothing recorded, never due again; its pool row is free for the next landmark
    assert h.counts([1])[0].tolist() == [0] and not h.complete[0] and h.row[0] == -1
    rows_before = h.pool_rows
    h.record_anchor([2], 2.0, I3, _C(2.0))
    assert h.pool_rows == rows_before


def test_full_history_stops_recording_and_memory_stays_bounded_over_a_stream_of_landmarks():
    h = ObservationHistory(4)
    h.record_anchor([1], 0.0, I3, _C(0.0))
    for k in range(1, 10):
        h.record_pixels([1], k, I3, _C(k), [[k, k]])
    assert h.counts([1])[0].tolist() == [4]
    assert np.allclose(h.gather([1])["t"], [0, 1, 2, 3])  # the first four kept
    # 30 live landmarks at a time over 3000 ids: rows are reused, the pool never exceeds what is alive (×2 growth)
    for k in range(3000):
        h.record_anchor([k + 10], float(k), I3, _C(k))
        if k >= 30:
            h.drop([k + 10 - 30])
    assert len(h) == 31 and h.pool_rows <= 64
    h.drop([10**9])  # unknown ids are ignored


def test_capacity_and_first_due_are_validated():
    for cap, first in ((1, 1), (True, 1), (8, 0), (8, 9), (8.0, 2)):
        with pytest.raises(InputError):
            ObservationHistory(cap, first)
