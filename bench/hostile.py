"""Hostile traffic and soak benchmark: the companion under a dirty MAVLink link for a long flight.

One lockstep SITL flight (:func:`flightsim.sitl.run_sitl`) of ``configs/scenarios/quad_hostile_hover.toml``
— the quad flies up to a textured warehouse face and hovers 6 m from it, sidestepping 1 m left and
right — lasting ``--minutes`` (the scenario's ``duration_s`` is rewritten and its sidestep repeated), with the simulated autopilot sending hostile datagrams
interleaved with its telemetry at ``--rate`` per simulated second (random bytes, bad CRC, truncated
packets, unknown message ids, NaN/inf payloads, glued packets, spoofed ATTITUDE from the vehicle's own
and from other ids: :mod:`flightsim.hostile`) and ``--blackouts`` telemetry blackouts of
``--blackout-s`` each, evenly spread after the warm-up (every second one silences the HEARTBEAT and the
answers to requests too, long enough for the companion to declare the link lost).

The companion is measured as a black box, from outside: its process (exit, RSS from
``/proc/PID/status`` VmRSS once per simulated second), its log (tracebacks) and the messages it sends
(``received.tlog``, stamped on arrival in simulation time).  Recorded and evaluated (targets ✓/✗):

* hostile datagrams and packets by kind (a glued datagram counts each of its parts as a packet);
* crashes — the companion exited or the run failed (target 0) — and tracebacks in its log (target 0);
* messages it sends per second by type, mean and worst window after the warm-up: STATUSTEXT at most
  1 in any 1-s window, COMMAND_LONG at most 1 in any 2-s window (0.5/s);
* RSS growth from minute 2 (or half the flight, if shorter) to the end (target ≤ 10 MiB);
* OBSTACLE_DISTANCE rate: worst 1-s window ≥ 80 % of the configured ``[outputs]
  autopilot_obstacle_distance_hz``, all flight long (unknown messages count: the rate must not stop);
* valid ranges while the telemetry is good: share of whole seconds after the warm-up, outside every
  blackout and the ``--settle-s`` after it, with at least one OBSTACLE_DISTANCE holding a range
  (target ≥ 99 %);
* per blackout: from its start until every sector is unknown and stays so to its end (target ≤ 0.5 s),
  and from its end until a range is published again (target ≤ ``--settle-s``).

``python -m bench.hostile --minutes 30 --rate 100 --json-out out/bench/hostile/hostile.json
--write docs/BENCHMARKS.md`` is the full run; ``--from-json FILE`` prints (and with ``--write``
writes) the section of an earlier run without flying again.
"""

from __future__ import annotations

import collections
import dataclasses
import datetime
import json
import math
import platform
import re
import shlex
import sys
import time
from pathlib import Path

from bench import report

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "configs" / "scenarios" / "quad_hostile_hover.toml"
OUT = ROOT / "out" / "bench" / "hostile"
SECTION = "## Hostile traffic and soak (issue 14)"

UINT16_MAX = 65535
RSS_GROWTH_MAX_MIB = 10.0
STATUSTEXT_PER_1S = 1  # at most this many STATUSTEXT texts in any 1-s window (chunks of one text count once)
COMMAND_LONG_PER_2S = 1  # at most this many COMMAND_LONG in any 2-s window (0.5/s)
BLACKOUT_UNKNOWN_MAX_S = 0.5
OD_RATE_MIN_FRACTION = 0.8
VALID_GOOD_MIN_SHARE = 0.99
WORKED_MIN_SHARE = 0.95  # frames the companion worked on (not dropped as stale): else the soak measured an idle process
FULL_RUN_MIN_MINUTES = 30.0
FULL_RUN_MIN_PACKETS = 100_000


@dataclasses.dataclass(frozen=True)
class Params:
    """What one benchmark run flies (the command-line options)."""

    minutes: float = 30.0  # flight time, simulated minutes
    rate: float = 100.0  # hostile datagrams per simulated second
    seed: int = 1  # the scenario's seed (flight) and the hostile traffic's seed
    blackouts: int = 4  # telemetry blackouts, evenly spread after the warm-up
    blackout_s: float = 4.0  # length of each, simulated s
    warmup_s: float = 20.0  # the approach and the first ranges: no blackout, not in the rate targets
    settle_s: float = 5.0  # after a blackout ends, the ranges must be back within this long
    processing_ms: float = 25.0  # lockstep: the companion's simulated processing time per frame
    kinds: tuple[str, ...] = ()  # hostile kinds (empty = all)

    @property
    def duration_s(self) -> float:
        return 60.0 * self.minutes


def blackout_plan(p: Params):
    """The blackout windows: ``p.blackouts`` of ``p.blackout_s`` evenly spread between the warm-up
    and the last ``settle_s`` + 2 s of the flight; every second one (the 2nd, 4th, …) also
    silences the HEARTBEAT."""
    from flightsim.hostile import Blackout

    if p.blackouts <= 0:
        return ()
    lo = p.warmup_s
    hi = p.duration_s - (p.settle_s + 2.0)
    span = hi - lo
    if span < p.blackouts * (p.blackout_s + p.settle_s):
        raise ValueError(f"{p.minutes:g} min leave no room for {p.blackouts} blackouts of {p.blackout_s:g} s after the "
                         f"{p.warmup_s:g} s warm-up (each needs {p.blackout_s + p.settle_s:g} s with its settling)")
    step = span / p.blackouts
    return tuple(Blackout(round(lo + (k + 0.5) * step - p.blackout_s / 2, 3), p.blackout_s, heartbeat=k % 2 == 1)
                 for k in range(p.blackouts))


def write_scenario(p: Params, out: Path) -> Path:
    """The scenario file with ``duration_s`` = ``p.minutes`` × 60, its sidestep (the last two waypoints
    and their holds) repeated until past the end of the flight, and its world path made absolute."""
    from companion.io.config_files import read_toml
    from flightsim.scenario import set_path_key

    text = SCENARIO.read_text(encoding="utf-8")
    route = read_toml(SCENARIO, "scenario")["vehicle"]["route"]
    wps, holds = [list(w) for w in route["waypoints"]], list(route["hold_s"])
    step = wps[-2:], holds[-2:]
    # each repeat takes at least its two holds: enough repeats for the longest flight, the surplus never flown
    while sum(holds) < p.duration_s:
        wps += step[0]
        holds += step[1]
    world = set_path_key(text, "world", "")[1]
    text, _ = set_path_key(text, "world", (SCENARIO.parent / world).resolve().as_posix())
    for key, val in (("duration_s", f"{p.duration_s:g}"),
                     ("waypoints", "[" + ", ".join("[" + ", ".join(f"{x:g}" for x in w) + "]" for w in wps) + "]"),
                     ("hold_s", "[" + ", ".join(f"{h:g}" for h in holds) + "]")):
        text, n = re.subn(rf"^{key} = .*$", lambda _m: f"{key} = {val}", text, count=1, flags=re.M)
        if n != 1:
            raise ValueError(f"{SCENARIO}: no one-line {key}")
    out.mkdir(parents=True, exist_ok=True)
    path = out / SCENARIO.name
    path.write_text(text, encoding="utf-8")
    return path


# ---------------------------------------------------------------------- measurements -------------
def read_received(path: Path, epoch_s: float) -> list[tuple[float, object]]:
    """Every message in a SITL ``received.tlog``: (arrival, simulation s; message)."""
    from companion.mavlink.dialect import mavutil

    if not Path(path).is_file():
        return []
    m = mavutil.mavlink_connection(str(path))
    out = []
    try:
        while (msg := m.recv_match()) is not None:
            if msg.get_type() == "BAD_DATA":
                continue
            out.append((msg._timestamp - epoch_s, msg))
    finally:
        m.close()
    return out


def worst_window(times: list[float], window: float, t0: float = -math.inf, t1: float = math.inf) -> int:
    """Most events in any half-open window ``[t, t + window)`` with ``t0 <= t`` and ``t + window <= t1``
    (windows starting at an event; ``times`` sorted)."""
    ts = [t for t in times if t0 <= t < t1]
    best, j = 0, 0
    for i, t in enumerate(ts):
        while j < len(ts) and ts[j] < t + window:
            j += 1
        best = max(best, j - i)
    return best


def min_window(times: list[float], window: float, t0: float, t1: float) -> int:
    """Fewest events in any window ``[t, t + window)`` with ``t0 <= t <= t1 - window``, ``t`` on a
    0.05 s grid offset by 1 µs (events on a regular clock never sit on a window's edge; ``times`` sorted)."""
    import bisect

    if t1 - t0 < window:
        return 0
    n_steps = int(math.floor((t1 - t0 - window) / 0.05 + 1e-9))
    best = None
    for k in range(n_steps + 1):
        t = t0 + 0.05 * k + 1e-6
        n = bisect.bisect_left(times, t + window) - bisect.bisect_left(times, t)
        best = n if best is None else min(best, n)
    return best or 0


def _valid(msg) -> bool:
    return any(d != UINT16_MAX for d in msg.distances)


def blackout_response(od: list[tuple[float, bool]], b, next_start: float) -> dict:
    """From OBSTACLE_DISTANCE arrivals ``(t, holds a range)``: when every sector went unknown for good
    during blackout ``b`` and when ranges came back after it (before ``next_start``)."""
    inside = [(t, v) for t, v in od if b.start_s <= t < b.end_s]
    last_valid = max((t for t, v in inside if v), default=None)
    after = [t for t, v in inside if not v and (last_valid is None or t > last_valid)]
    to_unknown = (after[0] - b.start_s) if after else None
    resumed = next((t for t, v in od if b.end_s <= t < next_start and v), None)
    return {"start_s": b.start_s, "end_s": b.end_s, "heartbeat": b.heartbeat,
            "to_all_unknown_s": None if to_unknown is None else round(to_unknown, 3),
            "valid_messages_inside": sum(1 for _, v in inside if v), "messages_inside": len(inside),
            "resume_s": None if resumed is None else round(resumed - b.end_s, 3)}


def log_stats(path: Path) -> dict:
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return {"lines": 0, "bytes": 0, "tracebacks": 0, "warnings": 0, "errors": 0, "readable": False}
    lines = text.splitlines()
    return {"lines": len(lines), "bytes": len(text.encode("utf-8", errors="replace")),
            "tracebacks": text.count("Traceback (most recent call last)"),
            "warnings": sum(1 for ln in lines if " WARNING " in ln), "errors": sum(1 for ln in lines if " ERROR " in ln
                                                                                  or " CRITICAL " in ln),
            "readable": True}


def rss_stats(samples, ref_t: float) -> dict:
    """RSS samples ``[t_s, wall_s, kiB]`` → growth from ``ref_t`` to the end, MiB, and a fitted slope."""
    if not samples:
        return {"samples": 0}
    ts = [s[0] for s in samples]
    mib = [s[2] / 1024.0 for s in samples]
    i_ref = next((i for i, t in enumerate(ts) if t >= ref_t), len(ts) - 1)
    tail_t, tail_m = ts[i_ref:], mib[i_ref:]
    slope = None
    if len(tail_t) >= 3 and tail_t[-1] > tail_t[0]:
        mt, mm = sum(tail_t) / len(tail_t), sum(tail_m) / len(tail_m)
        var = sum((t - mt) ** 2 for t in tail_t)
        slope = sum((t - mt) * (m - mm) for t, m in zip(tail_t, tail_m)) / var * 3600.0 if var > 0 else None
    per_min = []
    for k in range(int(ts[-1] // 60) + 1):
        j = next((i for i, t in enumerate(ts) if t >= 60.0 * k), None)
        if j is not None:
            per_min.append([k, round(mib[j], 2)])
    return {"samples": len(samples), "ref_t_s": round(ts[i_ref], 1), "ref_mib": round(mib[i_ref], 2),
            "end_t_s": round(ts[-1], 1), "end_mib": round(mib[-1], 2), "max_mib": round(max(mib), 2),
            "first_mib": round(mib[0], 2), "growth_mib": round(mib[-1] - mib[i_ref], 2),
            "max_growth_mib": round(max(tail_m) - mib[i_ref], 2),
            "slope_mib_per_h": None if slope is None else round(slope, 2), "per_minute_mib": per_min}


def analyse(run_dir: Path, p: Params, blackouts, *, epoch_s: float, od_rate_hz: float, flown_s: float) -> dict:
    """Every measurement of the module docstring from a run directory (``received.tlog``, ``companion.log``)."""
    run_dir = Path(run_dir)
    rx = read_received(run_dir / "received.tlog", epoch_s)
    end = flown_s
    w0 = p.warmup_s
    by_type: dict[str, list[float]] = collections.defaultdict(list)
    texts: list[tuple[float, str, int]] = []  # (arrival of its first chunk, text, chunks)
    commands: collections.Counter[str] = collections.Counter()
    od: list[tuple[float, bool]] = []
    for t, m in rx:
        typ = m.get_type()
        by_type[typ].append(t)
        if typ == "STATUSTEXT":  # a text longer than 50 characters comes in chunks with the same id
            if m.id and m.chunk_seq > 0 and texts and texts[-1][2] == m.id:
                t0, txt, _ = texts[-1]
                texts[-1] = (t0, txt + m.text, m.id)
            else:
                texts.append((t, m.text, m.id))
        elif typ == "COMMAND_LONG":
            commands[f"{m.command} param1={m.param1:g}"] += 1
        elif typ == "OBSTACLE_DISTANCE":
            od.append((t, _valid(m)))
    span = max(end - w0, 1e-9)

    def rates(times: list[float]) -> dict:
        after = [t for t in times if t >= w0]
        return {"count": len(times), "count_after_warmup": len(after), "mean_per_s": round(len(after) / span, 3),
                "worst_1s": worst_window(times, 1.0), "worst_1s_after_warmup": worst_window(times, 1.0, w0),
                "worst_2s_after_warmup": worst_window(times, 2.0, w0)}

    per_text: dict[str, list[float]] = collections.defaultdict(list)
    for t, txt, _ in texts:  # one text, whatever count of held-back repeats it reports
        per_text[re.sub(r" \(\+\d+ in [^)]*\)$", "", txt)].append(t)
    worst_text = max(((worst_window(ts, 1.0, w0), txt) for txt, ts in per_text.items()), default=(0, None))
    others = sorted(t for typ, ts in by_type.items() if typ not in ("STATUSTEXT", "COMMAND_LONG") for t in ts)
    messages = {"STATUSTEXT": rates(by_type.get("STATUSTEXT", [])), "statustext_texts": rates([t for t, _, _ in texts]),
                "statustext_one_text_worst_1s_after_warmup": {"count": worst_text[0], "text": worst_text[1]}, "COMMAND_LONG": rates(by_type.get("COMMAND_LONG", [])),
                "others": rates(others), "by_type": {k: rates(v) for k, v in sorted(by_type.items())}}
    od_times = [t for t, _ in od]
    gaps = [b - a for a, b in zip(od_times, od_times[1:]) if a >= w0]
    od_stats = {"configured_hz": od_rate_hz, "count": len(od_times),
                "mean_hz": round(sum(1 for t in od_times if t >= w0) / span, 3),
                "worst_1s_after_warmup": min_window(od_times, 1.0, w0, end),
                "longest_gap_s": round(max(gaps), 3) if gaps else None,
                "valid_share": round(sum(1 for _, v in od if v) / len(od), 4) if od else None}
    # valid ranges while the telemetry is good: whole seconds after the warm-up, outside blackouts + settle_s
    bad = [(b.start_s, b.end_s + p.settle_s) for b in blackouts]
    valid_secs = {int(t) for t, v in od if v}
    good = [s for s in range(int(math.ceil(w0)), int(end)) if s + 1 <= end
            and not any(s < hi and s + 1 > lo for lo, hi in bad)]
    with_valid = sum(1 for s in good if s in valid_secs)
    good_msgs = [(t, v) for t, v in od if t >= w0 and not any(lo <= t < hi for lo, hi in bad)]
    valid_good = {"good_seconds": len(good), "with_valid": with_valid,
                  "share": round(with_valid / len(good), 4) if good else None,
                  "messages": len(good_msgs), "messages_valid": sum(1 for _, v in good_msgs if v),
                  "seconds_without": [s for s in good if s not in valid_secs][:50]}
    starts = [b.start_s for b in blackouts] + [math.inf]
    bl = [blackout_response(od, b, starts[i + 1]) for i, b in enumerate(blackouts) if b.start_s < end]
    top = collections.Counter(txt for _, txt, _ in texts).most_common(12)
    return {"received": len(rx), "messages": messages, "statustext_top": top,
            "command_long": dict(commands.most_common(12)), "obstacle_distance": od_stats,
            "valid_while_good": valid_good, "blackouts": bl, "log": log_stats(run_dir / "companion.log")}


def evaluate(res: dict) -> list[dict]:
    """The targets, each ``{"name", "value", "bound", "met"}``."""
    m = res["metrics"]
    msg = m["messages"]
    od = m["obstacle_distance"]
    rss = m.get("rss") or {}
    vg = m["valid_while_good"]
    p = res["params"]
    T = []

    def add(name, value, bound, met):
        T.append({"name": name, "value": value, "bound": bound, "met": bool(met)})

    add("companion crashes (exited or the run failed)", res["crashes"], "= 0", res["crashes"] == 0)
    add("tracebacks in the companion's log", m["log"]["tracebacks"], "= 0", m["log"]["tracebacks"] == 0)
    acks = (res.get("sitl") or {}).get("acks") or {}
    n_acks = sum(acks.values())
    worked = (n_acks - acks.get("dropped", 0)) / n_acks if n_acks else None
    add("frames the companion worked on (processed or rejected, not dropped as stale)", worked,
        f"≥ {WORKED_MIN_SHARE:.0%}", worked is not None and worked >= WORKED_MIN_SHARE)
    st = msg["statustext_texts"]["worst_1s_after_warmup"]  # texts: a text over 50 characters is two chunks of one STATUSTEXT
    add("STATUSTEXT texts, most in any 1 s (chunks of one text count once)", st, f"≤ {STATUSTEXT_PER_1S}",
        st <= STATUSTEXT_PER_1S)
    cl = msg["COMMAND_LONG"]["worst_2s_after_warmup"]
    add("COMMAND_LONG, most in any 2 s", cl, f"≤ {COMMAND_LONG_PER_2S} (0.5/s)", cl <= COMMAND_LONG_PER_2S)
    g = rss.get("growth_mib")
    add(f"RSS growth from {rss.get('ref_t_s', '?')} s to the end, MiB", g, f"≤ {RSS_GROWTH_MAX_MIB:g}",
        g is not None and g <= RSS_GROWTH_MAX_MIB)
    need = OD_RATE_MIN_FRACTION * od["configured_hz"]
    add("OBSTACLE_DISTANCE, fewest in any 1 s", od["worst_1s_after_warmup"], f"≥ {need:g}",
        od["worst_1s_after_warmup"] >= need)
    add("seconds of good telemetry with a valid range", vg["share"], f"≥ {VALID_GOOD_MIN_SHARE:.0%}",
        vg["share"] is not None and vg["share"] >= VALID_GOOD_MIN_SHARE)
    for i, b in enumerate(m["blackouts"], 1):
        u = b["to_all_unknown_s"]
        add(f"blackout {i}: start → every sector unknown, s", u, f"≤ {BLACKOUT_UNKNOWN_MAX_S:g}",
            u is not None and u <= BLACKOUT_UNKNOWN_MAX_S)
        r = b["resume_s"]
        add(f"blackout {i}: end → valid ranges again, s", r, f"≤ {p['settle_s']:g}", r is not None and r <= p["settle_s"])
    return T


# ---------------------------------------------------------------------- the run -------------------
def _line_progress(total_s: float, stream=sys.stderr):
    """A progress callback for run_sitl: one line per ~5 % of the flight (simulated minutes, wall time)."""
    t0 = time.perf_counter()
    state = {"next": 0.0}

    def tick(frames_sent: int, n_frames: int) -> None:
        frac = frames_sent / max(n_frames, 1)
        if frac + 1e-9 >= state["next"]:
            state["next"] = frac + 0.05
            wall = time.perf_counter() - t0
            eta = wall / frac * (1 - frac) if frac > 0 else math.nan
            print(f"hostile: {100 * frac:5.1f} % — {frac * total_s / 60:.1f} of {total_s / 60:.1f} min flown, "
                  f"{wall / 60:.1f} min wall" + (f", ~{eta / 60:.0f} min left" if math.isfinite(eta) else ""),
                  file=stream, flush=True)

    return tick


def _commit() -> str | None:
    """The checkout's commit (``+dirty`` with uncommitted changes to tracked files), None outside git."""
    import subprocess

    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return rev + ("+dirty" if dirty else "") if rev else None


def run(p: Params, out: Path = OUT, *, companion_config=None, progress=None, command: str | None = None) -> dict:
    """Fly the benchmark (module docstring) into ``out`` and return the results."""
    from companion.io.config_files import load_companion_config
    from flightsim.hostile import KINDS, HostileConfig
    from flightsim.scenario import load_scenario, resolve_companion_config
    from flightsim.sitl import SitlConfig, SitlError, run_sitl

    out = Path(out)
    blackouts = blackout_plan(p)
    scen = write_scenario(p, out)
    sc = load_scenario(scen, seed=p.seed)
    cc = resolve_companion_config(sc, companion_config)
    od_hz = load_companion_config(cc).outputs.autopilot_obstacle_distance_hz
    hostile = HostileConfig(rate_hz=p.rate, seed=p.seed, kinds=tuple(p.kinds) or KINDS, blackouts=blackouts)
    cfg = SitlConfig(processing_ms=p.processing_ms, hostile=hostile, rss_sample_s=1.0)
    run_dir = out / "run"
    t0 = time.perf_counter()
    crash, summary, partial = None, None, None
    try:
        summary = run_sitl(scen, run_dir, seed=p.seed, companion_config=cc, config=cfg, score=False, progress=progress)
    except SitlError as exc:
        crash = str(exc)
        partial = exc.partial or {}
    wall = time.perf_counter() - t0
    if summary is not None:
        flown = float(summary["duration_s"])
        hostile_res = summary.get("hostile") or {}
        rss = summary.get("companion_rss_kib") or []
        exit_code = summary.get("companion_exit_code")
        killed = bool((summary.get("companion") or {}).get("killed"))
        sitl = {k: summary.get(k) for k in ("frames", "acks", "realtime_factor", "loop_wall_s", "wall_s", "cpu_s",
                                            "messages_sent", "autopilot_counters", "endpoint_counters")}
        sitl["clock_mismatches"] = summary["checks"].get("clock_mismatches", 0)
    else:
        flown = float(partial.get("t_s") or 0.0)
        hostile_res = {**(partial.get("hostile") or {}), "blackout_dropped": partial.get("blackout_dropped")}
        rss = partial.get("companion_rss_kib") or []
        exit_code = partial.get("companion_exit_code")
        killed = False
        sitl = {"frames": partial.get("frames"), "failure": crash}
    crashes = int(crash is not None or exit_code not in (0, None) or killed)
    metrics = analyse(run_dir, p, blackouts, epoch_s=sc.meta.epoch_s, od_rate_hz=od_hz, flown_s=flown)
    metrics["rss"] = rss_stats(rss, min(120.0, flown / 2))
    res = {"command": command, "date": datetime.date.today().isoformat(), "commit": _commit(),
           "machine": f"Python {platform.python_version()}, {platform.machine()}",
           "params": dataclasses.asdict(p) | {"kinds": list(p.kinds) or list(KINDS)},
           "scenario": str(SCENARIO.relative_to(ROOT)), "companion_config": str(cc) if cc else None,
           "out": str(out), "flown_s": flown, "wall_s": round(wall, 1), "crashes": crashes, "crash": crash,
           "companion_exit_code": exit_code, "hostile": hostile_res, "sitl": sitl, "metrics": metrics,
           "rss_samples_kib": rss}
    res["targets"] = evaluate(res)
    return res


# ---------------------------------------------------------------------- report -------------------
def _v(v, fmt="{:g}") -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and not math.isfinite(v):
        return "–"
    return fmt.format(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def markdown(res: dict) -> str:
    """The section of docs/BENCHMARKS.md (without its heading)."""
    p = res["params"]
    m = res["metrics"]
    h = res.get("hostile") or {}
    msg = m["messages"]
    od = m["obstacle_distance"]
    rss = m.get("rss") or {}
    vg = m["valid_while_good"]
    sitl = res.get("sitl") or {}
    full = p["minutes"] >= FULL_RUN_MIN_MINUTES and (h.get("packets") or 0) >= FULL_RUN_MIN_PACKETS
    L = [f"Command: `{res.get('command') or 'python -m bench.hostile'}` ({res['date']}, "
         + (f"commit {res['commit']}, " if res.get("commit") else "") + f"{res['machine']}; "
         f"{res['wall_s'] / 60:.1f} min wall"
         + (f", {sitl['realtime_factor']:.2f}× real time" if sitl.get("realtime_factor") else "") + ").",
         "",
         f"Lockstep SITL of `{res['scenario']}` (the quad flies 28 m at 3 m/s up to a textured warehouse face and hovers "
         f"6 m from it, sidestepping 1 m left and right with 3 s pauses) for **{res['flown_s'] / 60:.1f} min** of flight, seed {p['seed']}, with hostile datagrams "
         f"interleaved with the autopilot's telemetry at {p['rate']:g} per simulated second (Poisson, seeded; "
         "`flightsim/hostile.py`) and "
         f"{len(m['blackouts'])} telemetry blackouts of {p['blackout_s']:g} s (every second one also silences the "
         "HEARTBEAT and the answers to requests). The companion is measured from outside: its exit, its log, its "
         "resident set (`/proc/PID/status` VmRSS, every simulated second) and the messages it sends (arrival times in "
         f"simulation time). Rate targets count from the end of the {p['warmup_s']:g} s warm-up."
         + ("" if full else f" **Short run**: the full run is ≥ {FULL_RUN_MIN_MINUTES:g} min and ≥ "
            f"{FULL_RUN_MIN_PACKETS:,} hostile packets."),
         "",
         "| hostile kind | datagrams |", "|---|---:|"]
    for k, v in (h.get("by_kind") or {}).items():
        L.append(f"| {k} | {v:,} |")
    parts = h.get("glued_parts") or {}
    L += [f"| **total** | **{h.get('datagrams', 0):,}** datagrams, **{h.get('packets', 0):,}** packets (glued parts: "
          + (", ".join(f"{k} {v:,}" for k, v in parts.items()) or "none") + ") |"]
    dropped = h.get("blackout_dropped") or {}
    if dropped:
        L += ["", "Vehicle messages not sent during the blackouts: " + ", ".join(f"{k} {v:,}" for k, v in dropped.items()) + "."]
    L += ["", "| target | measured | bound | |", "|---|---:|---|---|"]
    for t in res["targets"]:
        val = t["value"]
        if isinstance(val, float) and (t["name"].startswith("seconds of good") or t["name"].startswith("frames the")):
            val = f"{100 * val:.2f} %"
        L.append(f"| {t['name']} | {_v(val)} | {t['bound']} | {'✓' if t['met'] else '✗'} |")
    L += ["", "Messages from the companion, per second after the warm-up (mean) and the most in any window:", "",
          "| message | count | mean /s | most in 1 s | most in 2 s | most in 1 s incl. start-up |", "|---|---:|---:|---:|---:|---:|"]
    rows = [("STATUSTEXT", msg["STATUSTEXT"]), ("COMMAND_LONG", msg["COMMAND_LONG"]), ("all others", msg["others"])]
    rows += [(f"· {k}", v) for k, v in msg["by_type"].items() if k not in ("STATUSTEXT", "COMMAND_LONG")]
    for name, r in rows:
        L.append(f"| {name} | {r['count']:,} | {r['mean_per_s']:.2f} | {r['worst_1s_after_warmup']} | "
                 f"{r['worst_2s_after_warmup']} | {r['worst_1s']} |")
    if m["statustext_top"]:
        tx, one = msg["statustext_texts"], msg["statustext_one_text_worst_1s_after_warmup"]
        L += ["", f"STATUSTEXT: {tx['count']:,} texts in {msg['STATUSTEXT']['count']:,} messages (a text over 50 characters "
              f"takes two); most texts in any 1 s after the warm-up {tx['worst_1s_after_warmup']}, of one text "
              f"{one['count']}" + (f" (“{one['text']}”)" if one["text"] else "") + ". Most frequent: "
              + "; ".join(f"“{t}” × {n}" for t, n in m["statustext_top"]) + "."]
    if m["command_long"]:
        L += ["", "COMMAND_LONG sent: " + "; ".join(f"{k} × {v}" for k, v in m["command_long"].items())
              + " (511 = SET_MESSAGE_INTERVAL, param1 the message id)."]
    L += ["", f"OBSTACLE_DISTANCE: {od['count']:,} messages, {od['mean_hz']:.2f}/s after the warm-up (configured "
          f"{od['configured_hz']:g} Hz), fewest in any 1 s {od['worst_1s_after_warmup']}, longest gap "
          f"{_v(od['longest_gap_s'])} s; {_v(None if od['valid_share'] is None else 100 * od['valid_share'], '{:.1f}')} % "
          f"hold a range. While the telemetry was good ({vg['good_seconds']} whole seconds after the warm-up, outside the "
          f"blackouts and the {p['settle_s']:g} s after each): {vg['with_valid']} of them had a valid range "
          f"({vg['messages_valid']:,} of {vg['messages']:,} messages)."
          + (f" Seconds without: {', '.join(map(str, vg['seconds_without'][:20]))}"
             + (" …" if len(vg["seconds_without"]) > 20 else "") + "." if vg["seconds_without"] else "")]
    if m["blackouts"]:
        L += ["", "| blackout | from, s | to, s | HEARTBEAT too | start → every sector unknown, s | ranges inside after that | end → ranges again, s |",
              "|---:|---:|---:|---|---:|---:|---:|"]
        for i, b in enumerate(m["blackouts"], 1):
            L.append(f"| {i} | {b['start_s']:g} | {b['end_s']:g} | {'yes' if b['heartbeat'] else 'no'} | "
                     f"{_v(b['to_all_unknown_s'])} | {b['valid_messages_inside']} of {b['messages_inside']} | {_v(b['resume_s'])} |")
    if rss.get("samples"):
        per = rss.get("per_minute_mib") or []
        step = max(1, len(per) // 12)
        L += ["", f"Companion RSS: {rss['first_mib']:.1f} MiB at the first sample, {rss['ref_mib']:.1f} MiB at "
              f"{rss['ref_t_s']:g} s, {rss['end_mib']:.1f} MiB at the end ({rss['end_t_s']:g} s), at most "
              f"{rss['max_mib']:.1f} MiB; growth {rss['growth_mib']:+.2f} MiB (largest above the reference "
              f"{rss['max_growth_mib']:+.2f} MiB), fitted slope {_v(rss['slope_mib_per_h'], '{:+.2f}')} MiB/h. "
              "Per minute: " + ", ".join(f"{k}: {v:.1f}" for k, v in per[::step]) + " MiB."]
    lg = m["log"]
    L += ["", f"Companion log: {lg['lines']:,} lines ({lg['bytes'] / 1024:.0f} KiB), {lg['warnings']:,} warnings, "
          f"{lg['errors']:,} errors, {lg['tracebacks']} tracebacks; exit code {_v(res.get('companion_exit_code'))}"
          + (f"; the run failed: {res['crash'].splitlines()[0]}" if res.get("crash") else "")
          + (f"; frames acknowledged: " + ", ".join(f"{k} {v:,}" for k, v in sorted(sitl['acks'].items()))
             if sitl.get("acks") else "")
          + (f"; lockstep clock mismatches (DISTANCE_SENSOR stamps off the simulation's clock model) "
             f"{sitl.get('clock_mismatches', 0):,}" if "clock_mismatches" in sitl else "") + "."]
    if sitl.get("clock_mismatches"):
        L += ["", f"The companion's DISTANCE_SENSOR stamps left the lockstep clock model {sitl['clock_mismatches']:,} times. "
              "With `--clock sim` the companion's clock is the newest autopilot time it has heard "
              "(`companion/simclock.py`), so one ATTITUDE accepted as the vehicle's with a far-future `time_boot_ms` "
              "moves it ahead for good: every later frame then looks stale and is dropped, and the outputs due on that "
              "clock stop (the likely cause when `spoof_attitude_own` is among the kinds)."]
    met = sum(1 for t in res["targets"] if t["met"])
    L += ["", f"Targets met: {met} of {len(res['targets'])}. Files: `{res['out']}/run/` (received.tlog, companion.log, "
          "sitl.json), results `--json-out`."]
    return "\n".join(L) + "\n"


def write_section(doc: Path, text: str) -> None:
    """Replace (or append) the section :data:`SECTION` of ``doc`` with ``text``."""
    report.write_section(doc, SECTION, text)


def main(argv=None) -> int:
    import argparse

    from flightsim.hostile import KINDS

    argv = list(sys.argv[1:] if argv is None else argv)
    d = Params()
    ap = argparse.ArgumentParser(prog="python -m bench.hostile", description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="examples:\n"
                                        "  python -m bench.hostile --minutes 2 --rate 100          # a short look\n"
                                        "  python -m bench.hostile --minutes 30 --rate 100 --json-out out/bench/hostile/hostile.json "
                                        "--write docs/BENCHMARKS.md\n"
                                        "  python -m bench.hostile --from-json out/bench/hostile/hostile.json --write docs/BENCHMARKS.md")
    ap.add_argument("--minutes", type=float, default=d.minutes, help=f"simulated flight time, minutes (default {d.minutes:g}; "
                                                                      f"the full run is ≥ {FULL_RUN_MIN_MINUTES:g})")
    ap.add_argument("--rate", type=float, default=d.rate, help=f"hostile datagrams per simulated second (default {d.rate:g})")
    ap.add_argument("--seed", type=int, default=d.seed, help=f"seed of the flight and of the hostile traffic (default {d.seed})")
    ap.add_argument("--blackouts", type=int, default=d.blackouts, help=f"telemetry blackouts (default {d.blackouts})")
    ap.add_argument("--blackout-s", type=float, default=d.blackout_s, help=f"length of each blackout, s (default {d.blackout_s:g})")
    ap.add_argument("--settle-s", type=float, default=d.settle_s,
                    help=f"ranges must be back this long after a blackout (default {d.settle_s:g})")
    ap.add_argument("--kinds", default=None, help=f"comma-separated subset of the hostile kinds (default all: {', '.join(KINDS)})")
    ap.add_argument("--processing-ms", type=float, default=d.processing_ms,
                    help=f"lockstep: simulated processing time per frame (default {d.processing_ms:g})")
    ap.add_argument("--config", metavar="TOML", default=None, help="companion configuration (default: the shipped one)")
    ap.add_argument("--out", default=str(OUT), help=f"run directory (default {OUT.relative_to(ROOT)})")
    ap.add_argument("--json-out", metavar="FILE", default=None, help="write the results to FILE (default OUT/hostile.json)")
    ap.add_argument("--json", action="store_true", help="print the results as JSON instead of the section")
    ap.add_argument("--write", metavar="DOC", default=None,
                    help=f"write the section '{SECTION[3:]}' into DOC (e.g. docs/BENCHMARKS.md), replacing an earlier one")
    ap.add_argument("--from-json", metavar="FILE", default=None, help="report an earlier run's results (no flight)")
    ap.add_argument("--quiet", action="store_true", help="no progress lines")
    args = ap.parse_args(argv)
    if args.from_json:
        res = json.loads(Path(args.from_json).read_text(encoding="utf-8"))
        res["targets"] = evaluate(res)
    else:
        if not (args.minutes > 0 and math.isfinite(args.minutes)):
            ap.error("--minutes must be > 0")
        if args.rate < 0:
            ap.error("--rate must be >= 0")
        kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip()) if args.kinds else ()
        bad = sorted(set(kinds) - set(KINDS))
        if bad:
            ap.error(f"unknown kind(s) {', '.join(bad)}; known: {', '.join(KINDS)}")
        p = Params(minutes=args.minutes, rate=args.rate, seed=args.seed, blackouts=args.blackouts,
                   blackout_s=args.blackout_s, settle_s=args.settle_s, processing_ms=args.processing_ms, kinds=kinds)
        try:
            blackout_plan(p)
        except ValueError as exc:
            ap.error(str(exc))
        command = "python -m bench.hostile " + shlex.join(argv)
        progress = None if args.quiet else _line_progress(p.duration_s)
        res = run(p, Path(args.out), companion_config=args.config, progress=progress, command=command)
        json_out = Path(args.json_out) if args.json_out else Path(args.out) / "hostile.json"
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(res, indent=1, default=str) + "\n", encoding="utf-8")
        print(f"results: {json_out}", file=sys.stderr)
    text = markdown(res)
    if args.write:
        write_section(Path(args.write), text)
        print(f"wrote the section into {args.write}", file=sys.stderr)
    print(json.dumps(res, default=str) if args.json else f"{SECTION}\n\n{text}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
