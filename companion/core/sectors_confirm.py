""""Clear" only once its evidence has lasted (docs/derivations/sectors.md, rule 11: confirmation over frames).

:func:`compute_sectors` judges every frame on its own.  A sector whose evidence of "clear" holds for a single
frame, between two frames that leave it unknown, is most often a rule's input crossing a threshold for one
frame: the band dropping from the climb's 30° to level as the climb rate falls through
``flight_path_min_speed_mps``, a veto point stepping out of its margin and back.  In the closed-loop pole
flights every dangerous clear left after the veto margins was such a single message (docs/BENCHMARKS.md,
"A ranged point beside the band").  :func:`confirm_clear` publishes "clear" only where the sector has been
clear in ``clear_confirm_frames`` consecutive frames; before that the sector is sent as unknown.

The count follows the world, not the body: between two frames the vehicle turns by Δψ, and new sector ``i``
covers the bearings old sectors ``i + ⌊Δψ/5°⌋`` and the next one covered (as :func:`rotate_sectors` maps
them).  It takes the smaller of their counts (the larger only where the shift is a whole number of sectors),
so a turn never confirms a direction faster than a hover would.  Pure: the caller keeps the count between
frames and starts it afresh (``None``) after a restart.  It only ever turns "clear" into unknown.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.core.sectors_types import (
    SECTOR_BEARING_DEG,
    SECTOR_COUNT,
    UNKNOWN_CM,
    ForwardRange,
    SectorConfig,
    Sectors,
    SectorState,
    UnknownReason,
    sector_shift,
)


def _carried(run_prev: np.ndarray, yaw_change_rad: float) -> np.ndarray:
    """The previous frame's consecutive-clear counts as seen from the current body frame (Δψ = yaw now −
    yaw then, + = turned right): new sector i takes the smaller count of the old sectors it overlaps."""
    lo, frac = sector_shift(yaw_change_rad)
    a = np.roll(run_prev, -lo)  # new[i] = old[i + lo]
    if frac < 1e-6:
        return a
    b = np.roll(run_prev, -(lo + 1))
    if frac > 1 - 1e-6:
        return b
    return np.minimum(a, b)


def confirm_clear(sectors: Sectors, run_prev: np.ndarray | None, yaw_change_rad: float,
                  config: SectorConfig) -> tuple[Sectors, np.ndarray]:
    """(sectors with "clear" withheld where not yet confirmed, the consecutive-clear count of each sector).

    ``run_prev`` is the count this function returned for the previous frame (``None`` at the start or after a
    restart); ``yaw_change_rad`` the vehicle's yaw change between the two frames' exposures (non-finite: the
    count starts afresh).  The count is of frames whose own rules said "clear", whether published or not;
    a sector is published clear once its count reaches ``config.clear_confirm_frames`` (1: every clear at once,
    the sectors returned unchanged).  A withheld sector becomes unknown (UINT16_MAX), and so does the forward
    reading when it was clear."""
    state = np.asarray(sectors.state)
    clear = state == SectorState.CLEAR
    if run_prev is None or not math.isfinite(yaw_change_rad):
        carried = np.zeros(SECTOR_COUNT, np.int64)
    else:
        carried = _carried(np.asarray(run_prev, np.int64), yaw_change_rad)
    run = np.where(clear, carried + 1, 0).astype(np.int64)
    withhold = clear & (run < config.clear_confirm_frames)
    if not withhold.any():
        return sectors, run
    dist = np.asarray(sectors.distances_cm).copy()
    new_state = state.copy()
    dist[withhold] = UNKNOWN_CM
    new_state[withhold] = SectorState.UNKNOWN
    forward = sectors.forward
    fwd = np.abs(SECTOR_BEARING_DEG) <= config.forward_half_width_deg + 1e-9
    if forward.state == SectorState.CLEAR and withhold[fwd].any():
        forward = ForwardRange(SectorState.UNKNOWN, math.nan, math.nan, math.nan)
    why = np.asarray(sectors.unknown_reason).copy()
    why[withhold] = UnknownReason.HELD
    return dataclasses.replace(sectors, distances_cm=dist, state=new_state, forward=forward, unknown_reason=why), run
