"""flightsim.score: scoring the companion's published ranges against the simulator's truth (docs/derivations/sectors.md).

Layers, each importing only the ones before it:

* :mod:`.config` — the ``[score]`` table (:class:`~.config.ScoreConfig`, configs/score.toml) and the cell codes;
* :mod:`.inputs` — :class:`~.inputs.RangeMessages` (the companion's messages as arrays) and
  :class:`~.inputs.SectorTruth` (the parts of ``truth.npz`` the score needs);
* :mod:`.obstacles` — truth cells grouped by position into obstacles, and named;
* :mod:`.stats` — χ² quantiles for the NEES band, the effective sample size of a correlated series
  and the ±kσ coverage (no SciPy at run time);
* :mod:`.evaluation` — every message against the truth (:func:`~.evaluation.evaluate` →
  :class:`~.evaluation.Evaluation`) and the cell categories (:func:`~.evaluation.cell_masks`);
* :mod:`.summary` — counts, rates, targets and tables: the JSON-ready score
  (:func:`~.summary.summarize`) and the per-message arrays a campaign pools;
* :mod:`.markdown` — ``score.md``;
* :mod:`.files` — the only one with I/O: reading the ranges tlog, ``truth.npz`` and
  configs/score.toml, writing ``score.json`` / ``score.md`` / ``score_series.npz``, and
  :func:`~.files.score_run`, the entry point (``flightsim score``, ``sitl``, ``campaign``).

Pure logic (all but :mod:`.files`): arrays in, arrays and a JSON-ready dict out.  :mod:`.files`
imports the others and nothing imports it back; this package module re-exports nothing.

What is scored
--------------
Every OBSTACLE_DISTANCE (and forward DISTANCE_SENSOR) the companion sent is compared with the
truth *of the moment it arrives*.  The forward readings come from the companion's sector log when it
carries them (``fwd`` on each line: the forward DISTANCE_SENSOR computed for that OBSTACLE_DISTANCE,
stamped with its arrival), since the companion withholds from the autopilot a forward reading that
disagrees with OBSTACLE_DISTANCE (docs/derivations/sectors.md); else from the DISTANCE_SENSORs
received (``score.json`` ``inputs.forward_readings`` says which).  The arrival: the record stamp of the message in the ranges tlog (the time it
left the companion in a replay, its arrival in SITL) picks the latest truth frame at or before
that stamp (``truth.npz`` ``t_s``, the same recording clock), if that frame is at most
``truth_max_age_s`` old; messages without such a frame are counted, not scored.  The companion
already turns its sectors to the yaw at sending time, so the truth sectors of that frame (body
FRD at the frame's own yaw, at most one frame period earlier) are compared as they are.

A *cell* is one (message, sector).  With ``T`` the true horizontal distance of the sector
(:mod:`flightsim.world.truth`: nearest obstacle footprint inside the ±2.5° wedge, within the
vertical band) and ``max`` the message's own ``max_distance``:

* **unknown-truth cell**: ``T`` is NaN (an older truth.npz knows only the sectors the camera
  sees); claims there are counted as *unscored claims*, nothing else;
* **obstacle cell**: ``T`` finite and ``T ≤ max``;
* **clear cell**: ``T`` is inf (nothing within the truth's ``sector_max_m``) or ``T > max``.

The published value of a sector is one of: *unknown* (UINT16_MAX), *clear* (``max + 1``), a
*range* ``r`` (``min_distance ≤ r ≤ max``, conservative: estimate − k·σ), or *invalid* (anything
else, e.g. below ``min_distance``; ArduPilot discards it).  The tolerance is
``tol(T) = max(tolerance_m, tolerance_rel · T)`` (defaults: max(2 m, 20 %)).

* **detection**: a range reported in an obstacle cell;
* **valid range**: a detection with ``|r − T| ≤ tol(T)``;
* **false obstacle**: a range reported in a clear cell nearer than the truth by more than ``tol``
  (``T − r > tol(T)``), or the same in an obstacle cell ("too near"); the first kind is the *false
  obstacle in a clear sector*.  Where ``T`` is inf the truth only says "beyond ``sector_max_m``",
  so it is taken at ``sector_max_m`` (the most favourable case): a range there is false when
  ``sector_max_m − r > tol(sector_max_m)`` and otherwise *unverifiable* (counted apart, neither
  right nor wrong; a truth horizon beyond the companion's ``max_distance`` removes the case);
* **over-range**: a detection farther than the truth by more than ``tol`` (``r − T > tol``);
* **dangerous clear**: "clear" (``max + 1``) reported in an obstacle cell — the most dangerous
  error: the autopilot is told the way is free while an obstacle stands within range.

Rates: detection rate = detections / obstacle cells; dangerous-clear rate = dangerous clears /
obstacle cells; false-obstacle rate (clear sectors) = false obstacles in clear cells / clear cells.
Per message: the share of messages *with no false obstacle in a clear sector*, over the messages
that make at least one claim (a range or "clear" in any sector) and have at least one clear cell
in view (an all-unknown message claims nothing and is not counted).

Over 360° (docs/derivations/sectors.md — an unknown sector means no constraint — and docs/derivations/obstacle_map.md — the
local map publishes remembered obstacles beside and behind the vehicle).  A truth.npz with
``sector_all_m`` and ``in_view`` knows every sector.  Cells in the camera's view are scored as
above.  Out of view only a *claim* is scored (a range or "clear"): a range within tolerance on an
obstacle cell is a (remembered) detection, too near in a clear cell a false obstacle, "clear" on
an obstacle cell a dangerous clear; unknown there is neutral (neither a cell nor a miss).  Counts
and rates are reported in view, out of view and pooled (``cells``/``rates`` are pooled), and the
safety targets are judged pooled.

*Remembered* cells (:func:`.evaluation.remembered_cells`): out-of-view obstacle cells whose obstacle (the
grouping below) was in view within ``remember_window_s`` with the vehicle moved less than
``remember_max_travel_m`` since, and whose own point (``remember_point``) was then in an in-view sector and
— with the scenario's world at hand, ``remember_visible`` — in the line of sight: no solid nearer than
max(``visible_tolerance_m``, ``visible_tolerance_rel`` · distance) short of it on the ray from the vehicle
(the far faces of a box passed along one side were in view but never seen; a thin pole's far side counts as
seen); their share reported within tolerance (unknown counts as not reported).  Detection by true range (``detection_bins_m``): per bin, in view and out of view (all
out-of-view obstacle cells), the share within tolerance, the share with any range, unknown and
clear.  Warm-up: messages stamped within ``warmup_s`` of the first truth frame are not scored
(cells, the forward DISTANCE_SENSOR and NEES); latency and the first claim include them.

*Rangeable* cells (:func:`.evaluation.rangeable_cells`; a diagnostic, not a target): the in-view
obstacle cells a single camera could have ranged at all, from how it moved.  The cell's point (its
true distance on its centre bearing, at the vehicle's altitude) lay in an in-view sector in some
truth frame at most ``rangeable_window_s`` earlier, from where its line of sight differs from the
present one by at least ``rangeable_parallax_deg`` (bearing parallax) or its distance by at least
the fraction ``rangeable_scale`` (looming), and — with the scenario's world, ``rangeable_visible`` —
where nothing hid it (the line of sight of the remembered cells).  A vehicle turning in place gains
neither.  Texture is not checked: it is the ceiling of any monocular method on that flight.  Reported
are its share of the in-view obstacle cells and the detection within tolerance among them, and
among the remembered cells those whose point was rangeable in the frame it was last in view (what
a map can only remember if it could range it then) with their share within tolerance.

Targets (thresholds in configs/score.toml): no false obstacle in clear sectors in
≥ 98 % of messages; dangerous clears ≤ 0.5 % of obstacle cells; false obstacles ≤ 1 % of clear
cells; detection (within tolerance) ≥ 90 % of in-view obstacle cells and ≥ 95 % of those within
``near_range_m``; remembered ≥ 90 %.  "Detection" in the range targets and the by-range tables
means a range *within tolerance* (``valid``); the ``detection`` rate below keeps its earlier
meaning (any range in an obstacle cell).

Range error by range bin (of the true distance ``T``), absolute and in % of ``T``: of the
conservative published value over all detections, and for the forward sector of the estimate
behind it, from DISTANCE_SENSOR: ``estimate = published + k·σ`` (``k`` = the companion's
``[sectors] sigma_k``).  σ comes from the message's ``covariance`` (variance in cm², 1…254) or,
since a uint8 variance cannot hold a σ above 16 cm (255 = unknown), from ``signal_quality``
``q = 100·(1 − (σ/d)/z)`` (``z`` = ``[outputs] quality_zero_rel_sigma``, ``d`` the published
range) when ``3 ≤ q ≤ 99`` (2 and 100 are saturated bounds); σ is then known to ±0.5 % of ``d``·z.
Published values clamped at ``min_distance`` or ``max_distance`` are not undone.  σ is the
companion's 3-D range σ applied to the horizontal range (rays within the flight band are nearly
horizontal).

NEES of the reported σ (forward sector): the samples ``(estimate − T)² / σ²`` of every scored
forward DISTANCE_SENSOR range with a known σ, averaged.  The estimate describes the exposure, so ``T``
is the truth of the capture frame when it is known (the DISTANCE_SENSOR is paired with the
OBSTACLE_DISTANCE sent with it, whose ``time_usec`` is the exposure); the NEES against the truth at
arrival is reported beside it (``arrival``).  If σ is right and the error Gaussian, each sample is
χ²₁ (mean 1, variance 2), and the mean of ``n`` *independent* samples lies in the two-sided band
``[χ²(n, 2.5 %), χ²(n, 97.5 %)] / n`` with 95 % probability (``nees_confidence``).

The samples are not independent: one filter carries its error over many frames (a landmark's range
error changes slowly), so consecutive NEES values are alike, and the mean of ``n`` of them varies
about as much as the mean of far fewer independent ones.  The score therefore estimates that
number, the *effective sample size* ``n_eff`` (:func:`.stats.effective_sample_size`):

* the NEES series is cut into *stretches* wherever two consecutive samples are more than
  ``nees_gap_s`` (0.5 s) apart — the forward range went unknown or clear, the filter may start
  afresh, and nothing says how the two sides relate;
* the autocorrelation ρ_k at lag k (in samples) is estimated from the pairs ``(i, i + k)`` inside a
  stretch only, about the mean of the whole run, averaged over all such pairs of all stretches;
* its sum is truncated by Geyer's *initial monotone sequence* (Geyer 1992): the sums of adjacent
  lags ``ρ_2m + ρ_2m+1`` are taken while they stay positive, none larger than the one before — past
  that point the estimates are noise.  ``τ = 1 + 2 Σ ρ_k`` is the *autocorrelation time*: how many
  samples are worth one independent sample;
* a stretch of ``m`` samples is worth ``m / (1 + 2 Σ_{k<m} (1 − k/m) ρ_k)`` (≈ ``m / τ`` when it is
  long), held within ``[1, m]`` — never more than independent samples, at least one; stretches are
  independent, and groups are combined so that the mean keeps the right variance:
  ``n_eff = n² / Σ (m² / n_eff,stretch)`` (:func:`.stats.pooled_n_eff`).

For an AR(1) series with coefficient φ this gives ``n (1 − φ)/(1 + φ)``; for its square (the NEES of
such an error) ``n (1 − φ²)/(1 + φ²)``.  Estimated from one run it is approximate — with a few
hundred samples and a long correlation it comes out somewhat high.  The band of the mean is then the
χ² band with ``n_eff`` degrees of freedom scaled by ``1/n_eff`` (``n_eff`` need not be an integer:
the χ² distribution with the mean 1 and variance ``2/n_eff`` of the correlated mean), and
``consistent`` says whether the mean lies in it.  The band of ``n`` independent samples is reported
beside it (``band_independent``, ``consistent_independent``) for reference only: it is far too
narrow for correlated samples.  The autocorrelation time, its last lag and the stretches are in the
score too.

Coverage of the reported σ: the share of the same samples whose truth lies within
``estimate ± σ`` and ``estimate ± 2σ`` (NEES ≤ 1, ≤ 4), beside what a Gaussian error with the right
σ gives, 68.27 % and 95.45 %.  It reads without the correlation: a lower share means σ too small (or
a heavier tail than Gaussian), a higher one σ too large.  The NEES mean is pulled by a few large
errors; the coverage is not.  Each scored run draws ``nees.png`` (:func:`flightsim.plots.nees_plot`):
the forward error over time inside its ±σ / ±2σ envelopes, and the running NEES mean against its
band for ``n_eff``.

A campaign pools the runs' samples: the pooled mean has ``n_eff = N² / Σ (n_run² / n_eff,run)`` —
the sum of the runs' ``n_eff`` when the runs share one autocorrelation time, less when a long,
strongly correlated run weighs on the pooled mean (``n_eff_sum_of_runs`` is reported beside it) —
and its coverage is that of all the samples.

Obstacles and time to the first valid range.  Truth sectors are grouped into obstacles by
position: the world point of every obstacle cell of every truth frame (vehicle position + ``T``
along the sector's centre bearing) is linked to every point within ``max(obstacle_link_m,
obstacle_link_rel · T)``; connected groups are obstacles (two solids closer than the link distance
merge into one).  With a world at hand (:func:`.obstacles.world_namer`) each group takes the name of the
solid nearest most of its points.  For each obstacle: the first message in which it occupies an
obstacle cell (``in range``), the first message with a valid range in one of its cells, the
difference (time to the first valid range), and the share of its in-range messages in which at
least one of its cells was detected.

Latency.  OBSTACLE_DISTANCE ``time_usec`` is the exposure on the autopilot's boot clock (µs; 0 =
no exposure behind it).  The companion's boot→recording offset is the lower envelope of
``stamp − time_boot_ms`` over its DISTANCE_SENSOR / NAMED_VALUE_FLOAT / OBSTACLE_DISTANCE_3D
messages (their ``time_boot_ms`` is the sending time); the mapped exposure snaps to the nearest
truth frame within ``capture_snap`` frame periods (its true capture time), and latency = stamp −
capture time.  p50 / p95 / p99 over messages with an exposure.
"""
