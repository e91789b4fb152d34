"""Readers and writers of the score: the companion's ranges tlog, ``truth.npz``,
``score.json`` / ``score.md`` / ``score_series.npz``, and ``configs/score.toml``.

The logic is in :mod:`flightsim.score`; this module only moves bytes.  A ranges tlog is a MAVLink 2
tlog (8-byte big-endian µs stamp + packed frame per record, see :mod:`flightsim.tlog`); only the
messages of the companion (component 196 by default) are read; corrupt records are skipped and
counted, never raised on.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import zipfile
from pathlib import Path

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.config import from_mapping
from companion.errors import ConfigError, InputError
from companion.io.atomic import StagedFiles, atomic_path
from companion.io.config_files import read_toml
from companion.io.inputs import check_input_file
from companion.io.tlog import read_tlog
from companion.sector_log import read_sector_lines
from flightsim.score.config import N_SECTORS, ScoreConfig
from flightsim.score.evaluation import evaluate
from flightsim.score.inputs import RangeMessages, SectorTruth
from flightsim.score.markdown import markdown
from flightsim.score.obstacles import world_namer, world_visibility
from flightsim.score.summary import message_sources, series_arrays, summarize

log = logging.getLogger(__name__)

COMPANION_COMPONENT = 196  # MAV_COMP_ID_OBSTACLE_AVOIDANCE (docs/derivations/link.md)
_BOOT_TYPES = ("DISTANCE_SENSOR", "NAMED_VALUE_FLOAT", "OBSTACLE_DISTANCE_3D")  # time_boot_ms = sending time


def read_ranges_tlog(path: str | Path, component_id: int = COMPANION_COMPONENT, system_id: int | None = None) -> RangeMessages:
    """The companion's messages in a tlog as :class:`RangeMessages`.

    The sender is component ``component_id`` of ``system_id`` (default: the system that sent the
    most OBSTACLE_DISTANCE from that component).  Records of other senders are counted as
    ``foreign``; unreadable ones as ``bad_records``.  A missing, empty or non-MAVLink file is a
    ConfigError; a file cut while being written is read up to its last whole record, with a warning.
    """
    contents = read_tlog(path)  # TlogError (a ConfigError) for a missing, empty or non-MAVLink file
    p = contents.path
    if contents.truncation:
        log.warning("%s", contents.truncation)
    counters: collections.Counter[str] = collections.Counter(contents.counters)
    rows: list[tuple[float, int, int, object]] = [
        (float(m._timestamp), m.get_srcSystem(), m.get_srcComponent(), m) for m in contents.messages]
    comp_rows = [r for r in rows if r[2] == component_id]
    if system_id is None and comp_rows:
        od_senders = collections.Counter(r[1] for r in comp_rows if r[3].get_type() == "OBSTACLE_DISTANCE")
        system_id = (od_senders or collections.Counter(r[1] for r in comp_rows)).most_common(1)[0][0]
    od, ds, boot, hb, texts = [], [], [], [], []
    by_type: collections.Counter[str] = collections.Counter()
    for t, src, comp, m in rows:
        if comp != component_id or src != system_id:
            counters["foreign"] += 1
            continue
        typ = m.get_type()
        by_type[typ] += 1
        try:
            if typ == "OBSTACLE_DISTANCE":
                d = np.asarray(m.distances, np.int64)
                inc = float(m.increment_f) if float(m.increment_f) > 0 else float(m.increment)  # ArduPilot's rule
                geometry_ok = bool(len(d) == N_SECTORS and abs(inc - 5.0) < 1e-6 and abs(float(m.angle_offset)) < 1e-6
                                   and int(m.frame) == mavlink.MAV_FRAME_BODY_FRD)
                od.append((t, int(m.time_usec), d, int(m.min_distance), int(m.max_distance), geometry_ok))
            elif typ == "DISTANCE_SENSOR":
                ds.append((t, int(m.current_distance), int(m.min_distance), int(m.max_distance), int(m.covariance),
                           int(getattr(m, "signal_quality", 0)), int(m.orientation)))
            elif typ == "HEARTBEAT":
                hb.append((t, int(m.system_status)))
            elif typ == "STATUSTEXT":
                txt = m.text if isinstance(m.text, str) else bytes(m.text).decode("ascii", "replace")
                texts.append((t, int(m.severity), txt.rstrip("\x00")))
            if typ in _BOOT_TYPES:
                boot.append((t, int(m.time_boot_ms)))
        except (AttributeError, TypeError, ValueError) as exc:
            counters["bad_fields"] += 1
            log.warning("%s: %s at %.3f s unusable (%s)", p, typ, t, exc)
    if not comp_rows:
        log.warning("%s: no message from component %d", p, component_id)
    counts = dict(counters)
    counts["by_type"] = dict(by_type)
    counts["system_id"] = system_id
    return RangeMessages.build(od, ds, boot, hb, texts, counts)


def read_truth_npz(path: str | Path) -> SectorTruth:
    """:class:`SectorTruth` from a flightsim ``truth.npz`` (``t_s``, ``sector_m``, ``p_ned``, ``rpy``, ``sector_max_m``).

    A truth over 360° (docs/derivations/obstacle_map.md) also holds ``sector_all_m`` (every sector, in view or
    not) and ``in_view`` (F, 72): then the score uses them; an older file has only ``sector_m``
    (NaN out of view) and out-of-view claims stay unscored.
    """
    p = check_input_file(path, "truth file")
    if not zipfile.is_zipfile(p):
        raise ConfigError(f"{p}: not a truth.npz (not a NumPy .npz archive)")
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = [k for k in ("t_s", "sector_m", "p_ned", "rpy", "sector_max_m") if k not in z.files]
            if missing:
                raise ConfigError(f"{p}: not a flightsim truth.npz (missing {', '.join(missing)})")
            rpy = np.asarray(z["rpy"], float)
            full = "sector_all_m" in z.files and "in_view" in z.files
            tr = SectorTruth(t_s=np.asarray(z["t_s"], float),
                             sector_m=np.asarray(z["sector_all_m" if full else "sector_m"], float),
                             p_ned=np.asarray(z["p_ned"], float), yaw=rpy[:, 2] if rpy.ndim == 2 and rpy.shape[1] == 3 else rpy,
                             sector_max_m=float(z["sector_max_m"]),
                             in_view=np.asarray(z["in_view"], bool) if full else None)
    except ConfigError:
        raise
    except InputError as exc:
        raise ConfigError(f"{p}: {exc}") from None
    except Exception as exc:  # not a zip, truncated, wrong dtype
        raise ConfigError(f"{p}: cannot read as truth.npz: {exc}") from None
    return tr


def load_score_config(path: str | Path | None) -> ScoreConfig:
    """The ``[score]`` table of a TOML file (defaults when ``path`` is None)."""
    if path is None:
        return ScoreConfig()
    p = Path(path)
    data = read_toml(p, "score configuration")
    unknown = sorted(set(data) - {"score"})
    if unknown:
        raise ConfigError(f"{p}: unknown table(s) {', '.join(map(repr, unknown))}; expected [score]")
    try:
        return from_mapping(ScoreConfig, data.get("score"), "score")
    except ConfigError as exc:
        raise ConfigError(f"{p}: {exc}") from None


def companion_score_params(companion_config) -> dict:
    """``sigma_k`` (with its taper: ``sigma_k_far``, ``sigma_k_taper_from_m``, ``sigma_k_taper_to_m``) and
    ``quality_zero_rel_sigma`` of a companion config (a CompanionConfig or a TOML path)."""
    cfg = companion_config
    if isinstance(cfg, (str, Path)):
        from companion.io.config_files import load_companion_config

        cfg = load_companion_config(cfg)
    sc = cfg.sectors
    return {"sigma_k": float(sc.sigma_k), "sigma_k_far": float(sc.sigma_k_far),
            "sigma_k_taper_from_m": float(sc.sigma_k_taper_from_m), "sigma_k_taper_to_m": float(sc.sigma_k_taper_to_m),
            "quality_zero_rel_sigma": float(cfg.outputs.quality_zero_rel_sigma)}


def forward_from_sector_log(msgs: RangeMessages, forward: dict) -> RangeMessages:
    """``msgs`` with its forward readings taken from the companion's sector log instead of the
    DISTANCE_SENSOR messages received: one reading per received OBSTACLE_DISTANCE whose log line
    carries one (:func:`companion.sector_log.read_sector_forward`), stamped with that message's
    arrival.  The companion sends the forward DISTANCE_SENSOR to the autopilot only when it agrees
    with OBSTACLE_DISTANCE (docs/derivations/sectors.md, "The forward DISTANCE_SENSOR and the
    autopilots"); a score of the forward range and its σ must not depend on that choice."""
    rows = []
    for i in range(len(msgs.od_t)):
        f = forward.get((int(msgs.od_time_usec[i]), msgs.od_distances_cm[i].astype(np.uint16).tobytes()))
        if f is not None:
            cm, cov, q = f
            rows.append((float(msgs.od_t[i]), cm, int(msgs.od_min_cm[i]), int(msgs.od_max_cm[i]), cov, q, 0))
    counts = dict(msgs.counts)
    counts["forward_from_sector_log"] = len(rows)
    counts["distance_sensor_received"] = int(len(msgs.ds_t))
    ds = RangeMessages.build(ds=rows)
    return dataclasses.replace(msgs, ds_t=ds.ds_t, ds_distance_cm=ds.ds_distance_cm, ds_min_cm=ds.ds_min_cm,
                               ds_max_cm=ds.ds_max_cm, ds_covariance=ds.ds_covariance, ds_quality=ds.ds_quality,
                               ds_orientation=ds.ds_orientation, counts=counts)


NEES_PLOT = "nees.png"
#: the companion's sector log in a run directory (``companion run --sector-log``; :mod:`companion.sector_log`)
SECTOR_LOG = "sectors.jsonl"
LANDMARK_LOG = "landmarks.jsonl"  # the companion's landmark log (flightsim sitl --landmark-log; companion/landmark_log.py)


def score_run(ranges_tlog, truth_npz, *, config: ScoreConfig | None = None, companion_config=None, world=None,
              component_id: int = COMPANION_COMPONENT, series_out=None, plot_dir=None, sector_log=None, **fields) -> dict:
    """Score one run: read the ranges tlog and ``truth.npz``, evaluate, summarize (the ``score.json``
    dict, with the avoidance outcome when a closed-loop ``trajectory.npz`` lies beside the truth).

    ``series_out``: where to write ``score_series.npz`` (None: not written).  ``plot_dir``: a
    directory, or a :class:`~companion.io.atomic.StagedFiles`, to draw ``nees.png`` into
    (:func:`flightsim.plots.plot_run_nees`: the forward error with its ±2σ envelope and the running
    NEES against its n_eff band); skipped without matplotlib; the score then names it under
    ``plots``.  ``sector_log``: the companion's sector log (default: ``sectors.jsonl`` beside the
    ranges tlog, used when present): the claims split by source (``claims_by_source``) and the unknown
    cells by reason (``unknown_by_reason``).
    ``fields`` override :class:`ScoreConfig` fields."""
    cfg = config or ScoreConfig()
    over = {}
    if companion_config is not None:
        over.update(companion_score_params(companion_config))
    unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(ScoreConfig)})
    if unknown:
        raise ConfigError(f"score_run: unknown option(s) {', '.join(unknown)}")
    over.update(fields)
    if over:
        cfg = dataclasses.replace(cfg, **{k: (tuple(v) if k in ("range_bins_m", "detection_bins_m") else v) for k, v in over.items()})
    msgs = read_ranges_tlog(ranges_tlog, component_id)
    truth = read_truth_npz(truth_npz)
    log_path = Path(ranges_tlog).with_name(SECTOR_LOG) if sector_log is None else Path(sector_log)
    lines = forward = reasons = None
    if log_path.is_file():
        try:
            lines, forward, reasons = read_sector_lines(log_path)  # one pass over the file
        except (InputError, OSError) as e:  # the score stands without it
            log.warning("sector log %s not read: %s", log_path, e)
    elif sector_log is not None:
        raise InputError(f"sector log {sector_log}: no such file")
    forward_source = "DISTANCE_SENSOR received"
    if forward:
        msgs = forward_from_sector_log(msgs, forward)
        forward_source = "sector log (every forward reading computed, sent to the autopilot or withheld)"
    visible = None if world is None else world_visibility(world, cfg.visible_tolerance_m, cfg.visible_tolerance_rel)
    ev = evaluate(msgs, truth, cfg, namer=world_namer(world) if world is not None else None, visible=visible)
    score = summarize(ev, lines, reasons)
    score["inputs"] = {"ranges": str(ranges_tlog), "truth": str(truth_npz), "forward_readings": forward_source}
    if lines is not None:
        score["inputs"]["sector_log"] = str(log_path)
    traj = Path(truth_npz).with_name("trajectory.npz")
    if traj.is_file():  # a closed-loop flight (flightsim.avoidance): its outcome
        from flightsim.outcome import evaluate_outcome, read_trajectory

        tr = read_trajectory(traj)
        if str(tr.get("avoidance_model", "none")) != "none":
            score["avoidance"] = evaluate_outcome(tr, world)
            score["inputs"]["trajectory"] = str(traj)
    if series_out is not None or plot_dir is not None:
        arrays = series_arrays(ev, message_sources(ev, reasons) if reasons else None)
        if series_out is not None:
            save_series(series_out, arrays)
        if plot_dir is not None:
            from flightsim.plots import plot_run_nees

            staged = isinstance(plot_dir, StagedFiles)
            directory = plot_dir.directory if staged else Path(plot_dir)
            target = plot_dir.path(NEES_PLOT) if staged else directory / NEES_PLOT
            if not staged:
                directory.mkdir(parents=True, exist_ok=True)
            if plot_run_nees(target, arrays, score["nees"], title=f"Forward σ of {directory.resolve().name}") is not None:
                score["plots"] = {"nees": NEES_PLOT}
    return score


def write_score(out_dir, score: dict) -> None:
    """``score.json`` and ``score.md`` into ``out_dir``, both at once (:func:`stage_score`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with StagedFiles(out) as staged:
        stage_score(staged, score)


def stage_score(staged: StagedFiles, score: dict) -> None:
    """Write ``score.json`` and ``score.md`` to their staged paths (they appear when ``staged`` commits)."""
    staged.path("score.json").write_text(json.dumps(score, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    staged.path("score.md").write_text(markdown(score, f"Score of {staged.directory.name}"), encoding="utf-8")


def save_series(path, arrays: dict) -> None:
    """``score_series.npz`` (compressed), written atomically."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(p) as tmp:
        np.savez_compressed(tmp, **arrays)


def load_series(path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
