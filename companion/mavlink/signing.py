"""MAVLink 2 message signing for the companion's links.

:func:`load_signing_key` reads the shared 32-byte secret; :class:`SigningPolicy` decides, for each
incoming packet, whether it is accepted, and counts why not.  :class:`companion.mavlink.link.MavLink`
installs it on its pymavlink parser (``mav.signing`` via ``setup_signing``) and signs everything it
sends (SHA-256 signature, 48-bit timestamp in 10 µs since 2015-01-01, its ``signing_link_id``).

Incoming packets (the MAVLink 2 signing rules, checked here instead of in pymavlink):

* signed with the right key and a timestamp newer than the last one accepted on the same stream
  (link id, system, component) — or, on a stream not seen before, no more than one minute older
  than our own timestamp — is accepted (``signed_ok``);
* signed with a wrong key or corrupted (``bad_signature``), replayed or reordered
  (``replayed``: the timestamp is not newer than the stream's last), or a new stream far in the
  past (``stale``) — always rejected;
* unsigned (including MAVLink 1) — rejected when ``require_signing``, else accepted and counted
  (``unsigned_accepted``: a migration mode while the other end is being set up).

Why not pymavlink's own ``check_signature``: it stores a stream's timestamp *before* checking the
signature, so one forged packet carrying a far-future timestamp makes every genuine packet of that
stream look replayed (denial of service); and its stream table has no bound.  Here a timestamp is
stored only after the signature verified, and at most ``max_streams`` streams are remembered (the
oldest is forgotten first).
"""

from __future__ import annotations

import collections
import hashlib
import re
from pathlib import Path

from companion.errors import ConfigError

#: One minute in signing timestamp units (10 µs): how far in the past a new stream may start.
NEW_STREAM_WINDOW = 6000 * 1000


def load_signing_key(path: str | Path) -> bytes:
    """The 32-byte MAVLink 2 signing secret from a key file.

    * exactly 32 bytes: the raw secret;
    * 64 hexadecimal digits (surrounding whitespace ignored): the secret in hex;
    * any other text: a passphrase (surrounding whitespace stripped), hashed with SHA-256 — the
      secret MAVProxy's ``signing setup <passphrase>`` derives, so both ends can share a phrase.

    A missing or unreadable file, an empty one, hex digits of the wrong length (a mistyped key)
    and an all-zero key (which autopilots read as "signing off") are :class:`ConfigError`.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"signing key file {p}: {exc.strerror or exc}") from None
    if len(data) == 32:
        key = data
    else:
        try:
            text = data.decode("utf-8").strip()
        except UnicodeDecodeError:
            raise ConfigError(f"signing key file {p}: {len(data)} bytes, neither 32 raw bytes nor text") from None
        if not text:
            raise ConfigError(f"signing key file {p} is empty")
        if re.fullmatch(r"[0-9a-fA-F]{64}", text):
            key = bytes.fromhex(text)
        elif re.fullmatch(r"[0-9a-fA-F]+", text) and len(text) >= 32:
            raise ConfigError(f"signing key file {p}: {len(text)} hex digits, a key in hex needs exactly 64")
        else:
            key = hashlib.sha256(text.encode("utf-8")).digest()
    if not any(key):
        raise ConfigError(f"signing key file {p}: an all-zero key means signing off")
    return key


class SigningPolicy:
    """Accept/reject decisions on signed and unsigned input (see the module docstring).

    ``install(mav)`` replaces the parser's signature check and unsigned callback; ``counters``
    hold ``signed_ok``, ``bad_signature``, ``replayed``, ``stale``, ``unsigned_rejected`` and
    ``unsigned_accepted``.  The stream table survives reconnections (a replay across a reopen of
    the port is still a replay).
    """

    def __init__(self, key: bytes, require_signing: bool, max_streams: int = 64):
        if not (isinstance(key, (bytes, bytearray)) and len(key) == 32):
            raise ConfigError("a MAVLink signing key is 32 bytes")
        self.key = bytes(key)
        self.require_signing = bool(require_signing)
        self.max_streams = int(max_streams)
        self.streams: collections.OrderedDict[tuple[int, int, int], int] = collections.OrderedDict()
        self.counters: collections.Counter[str] = collections.Counter()
        self._failed: str | None = None  # why the signature check of the packet being decoded failed

    def install(self, mav) -> None:
        """Use this policy on a pymavlink ``MAVLink`` parser whose ``signing`` is set up."""
        mav.check_signature = lambda msgbuf, src_system, src_component: self.check(mav, msgbuf, src_system, src_component)
        mav.signing.allow_unsigned_callback = self.allow_unsigned

    def check(self, mav, msgbuf, src_system: int, src_component: int) -> bool:
        """A signed packet (CRC already good): True if its signature and timestamp are acceptable."""
        self._failed = None
        try:
            link_id = msgbuf[-13]
            timestamp = int.from_bytes(bytes(msgbuf[-12:-6]), "little")
        except (IndexError, TypeError):
            self._failed = "bad_signature"
            return False
        stream = (int(link_id), int(src_system), int(src_component))
        last = self.streams.get(stream)
        if last is not None and timestamp <= last:
            self._failed = "replayed"
            return False
        if last is None and timestamp + NEW_STREAM_WINDOW < mav.signing.timestamp:
            self._failed = "stale"
            return False
        h = hashlib.sha256()
        h.update(self.key)
        h.update(bytes(msgbuf[:-6]))
        if h.digest()[:6] != bytes(msgbuf[-6:]):
            self._failed = "bad_signature"
            return False
        self.streams[stream] = timestamp  # only now: a forged packet cannot move a stream's timestamp
        self.streams.move_to_end(stream)
        while len(self.streams) > self.max_streams:
            self.streams.popitem(last=False)
            self.counters["streams_forgotten"] += 1
        mav.signing.timestamp = max(mav.signing.timestamp, timestamp)
        self.counters["signed_ok"] += 1
        return True

    def allow_unsigned(self, mav, msg_id: int) -> bool:
        """pymavlink's callback for every packet not accepted by :meth:`check` (unsigned or failed)."""
        failed, self._failed = self._failed, None
        if failed is not None:
            self.counters[failed] += 1
            return False
        if self.require_signing:
            self.counters["unsigned_rejected"] += 1
            return False
        self.counters["unsigned_accepted"] += 1
        return True


__all__ = ["load_signing_key", "SigningPolicy", "NEW_STREAM_WINDOW"]
