"""Drawing a :class:`~companion.monitor.state.Snapshot` (pure; rich is imported only when drawing).

:func:`render` gives a rich renderable (a Panel): health and link, a 72-sector strip (red near /
yellow mid / green far and clear / grey unknown; :class:`SectorStrip`), the nearest obstacle, the
forward range, diagnostics, STATUSTEXTs, rates and errors.  Stale data is drawn grey and labelled
STALE, never as current.  :func:`render_text` prints the same view as text (``--once``, pipes, tests).
"""

from __future__ import annotations

import io
import math

import numpy as np

from companion.mavlink.dialect import mavlink  # first: MAVLink 2 + ardupilotmega
from companion.core.sectors import SECTOR_COUNT, SectorState, UnknownReason
from companion.monitor.decode import DecodedSectors, bin_sectors, severity_name, state_name
from companion.monitor.state import MonitorConfig, Snapshot

#: Friendly labels for the companion's own diagnostics (:attr:`companion.reporter.Reporter.DIAG_NAMES`).
DIAG_LABELS = {"MR_FPS": "fps", "MR_TRACKS": "tracks", "MR_NEAR_M": "nearest m", "MR_LAT_MS": "latency ms",
               "MR_MAP": "map points", "MR_MEM_SEC": "sectors from memory", "MR_INFER": "inferred sectors",
               "MR_FWD_M": "forward m", "MR_FWD_SIG": "forward σ m", "MR_FWD_WHY": "forward unknown:"}


def reason_name(code: float) -> str:
    """An :class:`~companion.core.sectors_types.UnknownReason` code (``MR_FWD_WHY``) as words: "ranging", "few far", …"""
    try:
        return UnknownReason(int(code)).name.lower().replace("_", " ")
    except (ValueError, OverflowError):
        return f"code {code:g}"


# ---------------------------------------------------------------------- rendering --------------
GLYPH_UNKNOWN = "·"
GLYPH_CLEAR = "○"
GLYPHS_NEAR_TO_FAR = "█▇▆▅▄▃▂▁"
STYLE_NEAR, STYLE_MID, STYLE_FAR, STYLE_UNKNOWN, STYLE_STALE = "bold red", "yellow", "green", "grey50", "grey42"


def sector_cells(state: np.ndarray, range_m: np.ndarray, max_m: float, near_m: float, mid_m: float) -> list[tuple[str, str]]:
    """(glyph, style) per bin: obstacles as a bar that is taller the nearer (8 levels up to
    ``max_m``), red below ``near_m``, yellow below ``mid_m``, green beyond; clear ○ green;
    unknown · grey."""
    frac = np.clip(np.nan_to_num(range_m, nan=max_m) / max_m, 0.0, 1.0)
    level = np.minimum((frac * len(GLYPHS_NEAR_TO_FAR)).astype(int), len(GLYPHS_NEAR_TO_FAR) - 1)
    out = []
    for s, r, lv in zip(state, range_m, level):
        if s == SectorState.OBSTACLE:
            out.append((GLYPHS_NEAR_TO_FAR[lv], STYLE_NEAR if r < near_m else STYLE_MID if r < mid_m else STYLE_FAR))
        elif s == SectorState.CLEAR:
            out.append((GLYPH_CLEAR, STYLE_FAR))
        else:
            out.append((GLYPH_UNKNOWN, STYLE_UNKNOWN))
    return out


class SectorStrip:
    """The sectors as one text line from −180° through the reference (centre) to +180°, with an
    axis line under it; 72 bins of 5° when there is room, else 36 or 18 (combined conservatively).
    Indented by ``indent`` columns (to line up with the view's values) when that still fits."""

    def __init__(self, sectors: DecodedSectors, config: MonitorConfig, stale: bool, indent: int = 0):
        self.sectors = sectors
        self.config = config
        self.stale = stale
        self.indent = indent

    def __rich_measure__(self, console, options):
        from rich.measure import Measurement

        return Measurement(SECTOR_COUNT // 4, min(options.max_width, SECTOR_COUNT + self.indent))

    def lines(self, width: int = SECTOR_COUNT):
        from rich.text import Text

        bins = next((b for b in (SECTOR_COUNT, SECTOR_COUNT // 2) if width >= b), SECTOR_COUNT // 4)
        pad = " " * max(0, min(self.indent, width - bins))
        state, rng = bin_sectors(self.sectors, bins)
        order = (np.arange(bins) + bins // 2) % bins  # display column k shows bearing −180° + k·360/bins
        cells = sector_cells(state[order], rng[order], self.sectors.max_distance_m, self.config.near_m, self.config.mid_m)
        strip = Text(pad, no_wrap=True)
        for glyph, style in cells:
            strip.append(glyph, STYLE_STALE if self.stale else style)
        north = self.sectors.reference == "north"
        marks = ("S", "W", "N", "E") if north else ("B", "L", "F", "R")
        axis = [" "] * bins
        for q, mark in enumerate(marks):
            axis[q * bins // 4] = mark
        for q in range(4):  # 45° ticks between the letters
            axis[q * bins // 4 + bins // 8] = "'"
        return [strip, Text(pad + "".join(axis), style="dim", no_wrap=True)]

    def __rich_console__(self, console, options):
        yield from self.lines(options.max_width)


def _age(a: float | None) -> str:
    if a is None:
        return "never"
    return f"{a:.2f} s ago" if a < 10 else f"{a:.0f} s ago"


def _bearing(b: float) -> str:
    return f"{b:+.0f}°"


def render(snap: Snapshot, source: str = ""):
    """A rich renderable (a Panel) of the snapshot; stale data is drawn grey and labelled STALE."""
    from rich.columns import Columns
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    c = snap.config
    label_w = 11

    def new_grid():
        g = Table.grid(padding=(0, 1))
        g.add_column(style="bold", no_wrap=True, min_width=label_w)
        g.add_column()
        return g

    parts = []
    grid = new_grid()

    # health / link
    link_style = {"ok": "green", "no_heartbeat": "yellow", "waiting": "grey50", "lost": "bold red"}[snap.link_state]
    h = Text()
    if snap.system_status is None:
        h.append("unknown", "grey50")
        h.append(" · no HEARTBEAT from the companion yet" if snap.link_state != "lost" else "")
    elif snap.health_current:
        st = state_name(snap.system_status)
        h.append(st, {"ACTIVE": "bold green", "STANDBY": "bold yellow"}.get(st, "bold red"))
        h.append(f" · heartbeat {_age(snap.heartbeat_age_s)}")
    else:
        h.append("unknown", "bold red")
        h.append(f" · last heartbeat {_age(snap.heartbeat_age_s)} said {state_name(snap.system_status)}", "grey50")
    link_text = {"ok": "link OK", "no_heartbeat": "NO HEARTBEAT", "lost": "LINK LOST",
                 "waiting": "waiting for its HEARTBEAT" if snap.heard else "waiting for the companion"}[snap.link_state]
    if snap.link_state == "lost":
        h.append(f" · LINK LOST (nothing for > {c.link_timeout_s:g} s)", "bold red")
    elif snap.link_state == "no_heartbeat":
        h.append(f" · NO HEARTBEAT for > {c.link_timeout_s:g} s (other messages arrive)", "bold yellow")
    grid.add_row("health", h)

    # sectors
    d = snap.sectors
    if d is None:
        grid.add_row("sectors", Text("no OBSTACLE_DISTANCE received", "grey50"))
    else:
        stale = snap.sectors_stale
        head = Text()
        if stale:
            head.append(f"STALE · last OBSTACLE_DISTANCE {_age(snap.sectors_age_s)}", "bold red")
        else:
            head.append(f"{_age(snap.sectors_age_s)}", "green")
            rate = snap.rates_hz.get("OBSTACLE_DISTANCE", math.nan)
            if math.isfinite(rate):
                head.append(f" · {rate:.1f} Hz")
        n = d.counts()
        head.append(f" · obstacle {n['obstacle']} · clear {n['clear']} · unknown {n['unknown']}", "grey50" if stale else "")
        grid.add_row("sectors", head)
        parts += [grid, SectorStrip(d, c, stale, indent=label_w + 1)]  # a row of its own: 72 columns fit in 80
        grid = new_grid()
        grid.add_row("", Text(f"{GLYPHS_NEAR_TO_FAR[0]} near … {GLYPHS_NEAR_TO_FAR[-1]} far  {GLYPH_CLEAR} clear  "
                              f"{GLYPH_UNKNOWN} unknown · red < {c.near_m:g} m, yellow < {c.mid_m:g} m", "dim"))
        grid.add_row("", Text(f"{SECTOR_COUNT} × {d.increment_deg:g}° (increment {d.increment}, increment_f {d.increment_f:g}) "
                              f"from {d.angle_offset_deg:g}°, frame {d.frame_name}, {d.min_distance_m:.2f}–{d.max_distance_m:.2f} m",
                              "dim"))
        for w in d.warnings:
            grid.add_row("", Text(f"! {w}", "yellow"))
        r, b, _ = d.nearest()
        near = Text()
        if not math.isfinite(r):
            near.append("none", "grey50" if stale else "green")
            near.append(" (no sector reports an obstacle)" + (" · STALE" if stale else ""), "grey50")
        elif stale:
            near.append("— STALE", "bold red")
            near.append(f" (was {r:.2f} m at {_bearing(b)} from {d.reference}, {_age(snap.sectors_age_s)})", "grey50")
        else:
            near.append(f"{r:.2f} m", STYLE_NEAR if r < c.near_m else STYLE_MID if r < c.mid_m else STYLE_FAR)
            near.append(f" at {_bearing(b)} from {d.reference}")
        grid.add_row("nearest", near)

    # forward DISTANCE_SENSOR
    f = snap.forward
    fw = Text()
    if f is None:
        fw.append("no forward DISTANCE_SENSOR received", "grey50")
    else:
        stale = snap.forward_stale
        if stale:
            fw.append("STALE ", "bold red")
        style = "grey50" if stale else ""
        if f.state == "obstacle":
            sig = f"± {f.sigma_m:.2f} m" if math.isfinite(f.sigma_m) else "± ? (σ unknown)"
            fw.append(f"{f.distance_m:.2f} m {sig}", style or "bold")
            q = {0: "unknown"}.get(f.signal_quality, str(f.signal_quality))
            fw.append(f" · quality {q}", style)
        elif f.state == "clear":
            fw.append(f"clear (beyond {f.max_distance_m:g} m)", style or "green")
        else:
            fw.append("unknown", style or "grey50")
        fw.append(f" · {_age(snap.forward_age_s)}", style)
    grid.add_row("forward", fw)

    # diagnostics
    diags = []
    for name, value, age in snap.diagnostics:
        label = DIAG_LABELS.get(name, name)
        old = age > max(3.0, c.link_timeout_s)
        if name == "MR_NEAR_M" and value < 0:
            shown = "none"
        elif name == "MR_FWD_WHY":
            if value == 0:
                continue  # the forward sector claims: nothing to explain
            shown = reason_name(value)
        elif math.isfinite(value) and value == int(value) and abs(value) < 1e9:
            shown = str(int(value))
        else:
            shown = f"{value:.4g}"
        diags.append(Text.assemble((f"{label} ", "grey50"), (shown, "grey50" if old else "bold"),
                                   (f" ({_age(age)})" if old else "", "grey50"), no_wrap=True))
    grid.add_row("diagnostics", Columns(diags, padding=(0, 2)) if diags else Text("none received", "grey50"))

    # STATUSTEXT
    if snap.statustext:
        st = Text()
        for k, (age, sev, text, _) in enumerate(snap.statustext):
            if k:
                st.append("\n")
            sev_style = "bold red" if sev <= mavlink.MAV_SEVERITY_ERROR else "yellow" if sev == mavlink.MAV_SEVERITY_WARNING else ""
            st.append(f"{_age(age):>11} ", "grey50")
            st.append(f"{severity_name(sev):<9} ", sev_style)
            st.append(text)
        grid.add_row("status text", st)
    else:
        grid.add_row("status text", Text("none received", "grey50"))

    # rates, traffic and errors
    rates = [Text.assemble(f"{name} ", (f"{hz:.1f} Hz" if math.isfinite(hz) else "… Hz", "bold"), no_wrap=True)
             for name, hz in snap.rates_hz.items()]
    grid.add_row("rates", Columns(rates, padding=(0, 2)) if rates else Text("nothing from the companion", "grey50"))
    if snap.other_messages or snap.other_companions:
        ot = Text(f"{snap.other_messages} message(s) from other components/systems", "grey50")
        if snap.other_sources:
            shown = ", ".join(f"{s}/{cc}" for s, cc in snap.other_sources[:6])
            ot.append(f" ({shown}{', …' if len(snap.other_sources) > 6 else ''})", "grey50")
        if snap.other_companions:
            ot.append(f" · other systems with component {c.component_id}: "
                      + ", ".join(map(str, snap.other_companions)) + " (choose one with --system)", "yellow")
        grid.add_row("other", ot)
    errs = [Text(f"{name.replace('_', ' ').replace('crc', 'CRC')} {n}", "yellow", no_wrap=True) for name, n in snap.errors.items()]
    grid.add_row("errors", Columns(errs, padding=(0, 2)) if errs else Text("none", "grey50"))

    who = f"{snap.system_id}/{c.component_id}" if snap.system_id is not None else f"?/{c.component_id}"
    title = Text.assemble((f"companion {who}", "bold"), " — ", (link_text, link_style))
    sub = f"{source} · {snap.elapsed_s:.1f} s · {snap.rx_bytes} bytes" if source else f"{snap.elapsed_s:.1f} s"
    parts.append(grid)
    return Panel(Group(*parts), title=title, title_align="left", subtitle=sub, subtitle_align="right", border_style=link_style,
                 expand=False)


def render_text(snap: Snapshot, source: str = "", width: int = 110, color: bool = False) -> str:
    """The view as text (no colour by default): for ``--once``, pipes and tests."""
    from rich.console import Console

    buf = io.StringIO()
    console = Console(file=buf, width=width, force_terminal=color, color_system="truecolor" if color else None,
                      legacy_windows=False, emoji=False, highlight=False)
    console.print(render(snap, source))
    return buf.getvalue()
