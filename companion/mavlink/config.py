"""The ``[link]`` table: :class:`LinkConfig`, the settings of the companion's MAVLink link (docs/derivations/link.md).

TIMESYNC settings are its ``[link.timesync]`` sub-table (:class:`~companion.mavlink.timesync.TimesyncConfig`).
Used by :mod:`companion.mavlink.link`, :mod:`.streams` and :mod:`.transport`.
"""

from __future__ import annotations

import dataclasses

from companion.config import require, require_finite
from companion.mavlink.timesync import TimesyncConfig


@dataclasses.dataclass(frozen=True)
class LinkConfig:
    """The ``[link]`` table (TIMESYNC settings in ``[link.timesync]``)."""

    baud: int = 921600  # serial baud rate (ignored by udp/tcp connection strings)
    system_id: int = 0  # own system id; 0 = use the vehicle's, learnt from its HEARTBEAT
    provisional_system_id: int = 1  # system id of our HEARTBEAT until the vehicle's is known (udpout must talk first)
    component_id: int = 196  # own component id (MAV_COMP_ID_OBSTACLE_AVOIDANCE)
    autopilot_component_id: int = 1  # component whose HEARTBEAT identifies the vehicle (MAV_COMP_ID_AUTOPILOT1)
    heartbeat_hz: float = 1.0  # own HEARTBEAT rate
    attitude_hz: float = 50.0  # ATTITUDE rate requested
    local_position_hz: float = 20.0  # LOCAL_POSITION_NED rate requested
    global_position_hz: float = 5.0  # GLOBAL_POSITION_INT rate requested
    command_timeout_s: float = 1.0  # wait this long for the COMMAND_ACK of SET_MESSAGE_INTERVAL
    command_retries: int = 3  # SET_MESSAGE_INTERVAL attempts per stream before falling back to REQUEST_DATA_STREAM
    rate_check_s: float = 2.5  # after an accepted request, the stream must reach its rate within this long
    rate_window_s: float = 2.0  # arrival rates are measured over this window
    min_rate_fraction: float = 0.5  # a stream below this fraction of its requested rate counts as not arriving
    fallback_repeat_s: float = 5.0  # REQUEST_DATA_STREAM is repeated this often while a fallback stream is missing
    link_timeout_s: float = 3.0  # no vehicle HEARTBEAT for this long = link lost
    reconnect_interval_s: float = 2.0  # serial / tcp reopen attempts while the link is lost or broken
    autopilot_system_id: int = 0  # system id of the autopilot to follow; 0 = the first vehicle HEARTBEAT's (then locked until restart)
    signing_key_file: str = ""  # MAVLink 2 signing key file; "" = no signing (32 raw bytes, 64 hex digits, or a passphrase hashed with SHA-256 like MAVProxy)
    require_signing: bool = False  # with a key: true = reject every unsigned packet; false = accept unsigned ones too (counted; wrongly signed are always rejected)
    signing_link_id: int = 1  # link id written into our signatures (the ground-station output uses the next one)
    max_signing_streams: int = 64  # signing timestamps remembered per (link id, system, component), oldest forgotten first
    max_messages_per_poll: int = 2000  # bound on messages handled by one poll()
    clock_jitter_s: float = 0.5  # time_boot_ms may go back, or run ahead of our clock, by this much and still be the autopilot's clock, s
    clock_lock_messages: int = 3  # agreeing time_boot_ms stamps needed to lock onto the autopilot's clock at start
    reboot_confirm_messages: int = 10  # stamps on a new clock needed before a reboot is declared ...
    reboot_confirm_s: float = 0.5  # ... spanning this long, with the old clock silent this long, s
    reboot_heartbeat_gap_s: float = 1.5  # a HEARTBEAT silence this long that ended after the old clock stopped confirms a reboot (else two message types must agree), s
    reboot_min_interval_s: float = 5.0  # at most one declared reboot per this long, s
    max_clock_candidates: int = 4  # time_boot_ms clocks other than the autopilot's tracked at once (for reboot detection)
    stream_request_interval_s: float = 2.0  # SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM: at most one per this long on average ...
    stream_request_burst: int = 5  # ... after a burst of at most this many (one per stream and data stream at start-up)
    timesync_answer_max_hz: float = 20.0  # answers to the autopilot's TIMESYNC requests at most this often
    max_sources: int = 32  # (system, component) sources counted in the per-source table; least recently heard evicted first
    max_udp_peers: int = 4  # udpin: addresses we send to (those that sent valid MAVLink from the vehicle), least recently heard evicted first
    max_events: int = 64  # state changes (for STATUSTEXT) held between two drains; older ones are dropped and counted
    timesync: TimesyncConfig = dataclasses.field(default_factory=TimesyncConfig)  # [link.timesync]

    def __post_init__(self) -> None:
        def _int(name: str, lo: int, hi: int) -> None:
            v = getattr(self, name)
            require(isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi, f"{name} must be an integer in [{lo}, {hi}], got {v!r}")

        _int("baud", 1, 100_000_000)
        _int("system_id", 0, 255)
        _int("provisional_system_id", 1, 255)
        _int("component_id", 1, 255)
        _int("autopilot_component_id", 1, 255)
        _int("command_retries", 1, 100)
        _int("autopilot_system_id", 0, 255)
        _int("signing_link_id", 0, 254)
        _int("max_signing_streams", 1, 65536)
        _int("max_messages_per_poll", 1, 1_000_000)
        _int("clock_lock_messages", 1, 1000)
        _int("reboot_confirm_messages", 2, 10000)
        _int("max_clock_candidates", 1, 64)
        _int("stream_request_burst", 1, 100)
        _int("max_sources", 2, 65536)
        _int("max_udp_peers", 1, 256)
        _int("max_events", 1, 100_000)
        for name in ("heartbeat_hz", "attitude_hz", "local_position_hz", "global_position_hz", "command_timeout_s",
                     "rate_check_s", "rate_window_s", "fallback_repeat_s", "link_timeout_s", "reconnect_interval_s",
                     "clock_jitter_s", "reboot_confirm_s", "reboot_heartbeat_gap_s", "reboot_min_interval_s",
                     "stream_request_interval_s", "timesync_answer_max_hz"):
            require_finite(name, getattr(self, name), positive=True)
        require_finite("min_rate_fraction", self.min_rate_fraction, positive=True)
        require(self.min_rate_fraction <= 1.0, "min_rate_fraction must be <= 1")
        require(self.clock_jitter_s <= 10.0, f"clock_jitter_s must be <= 10 s, got {self.clock_jitter_s}")
        require(self.reboot_min_interval_s >= self.reboot_confirm_s,
                "reboot_min_interval_s must be >= reboot_confirm_s")
        require(isinstance(self.signing_key_file, str), "signing_key_file must be a string")
        require(isinstance(self.require_signing, bool), "require_signing must be true or false")
        require(not self.require_signing or bool(self.signing_key_file.strip()),
                "require_signing = true needs signing_key_file (a 32-byte key: raw, or 64 hex digits)")
        require(isinstance(self.timesync, TimesyncConfig), "timesync must be a [link.timesync] table")
