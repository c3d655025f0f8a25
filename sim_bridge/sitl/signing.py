"""The SITL's MAVLink 2 signing set-up (docs/signing.md): one key and timestamp file for the
process, one replay table per vehicle, and a signing layer per endpoint.

Vehicle k's endpoint (link id k) and the shared GCS endpoint (link id n) check a signed
frame against the replay table of the vehicle it is for (companion.link.signing.FleetScope):
a frame captured on one of them is a replay on the other, and a vehicle's own frames sent
back to it are replays. A frame that names no target is also checked against one table
shared by the vehicle endpoints, so that one captured on vehicle 1's endpoint is a replay
on vehicle 2's. The simulated radio signs only its own marker (link id 200) and keeps a
table of its own.
"""
from __future__ import annotations

import os
from typing import Callable

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from companion.link.msgdef import swarmdrop  # noqa: E402
from companion.link.signing import (  # noqa: E402
    STREAMS_MAX,
    FleetScope,
    ReplayTable,
    Signing,
    SigningError,
    TimestampStore,
    load_key,
    target_system_offsets,
)
from sim_bridge.sitl.config import SigningConfig  # noqa: E402

RADIO_LINK_ID = 200


class SitlSigning:
    """Signing layers for the SITL's endpoints.

    Args:
        cfg: the signing section of the SITL config.
        n: vehicles.
        crc_extra: the codec's msgid -> CRC_EXTRA.
        on_setup_refused: called with (vehicle index, reason) for every SETUP_SIGNING an
            endpoint's signing layer drops (the SITL counts and answers it).
    Raises:
        SigningError: a signing mode without a usable key file (before any port opens).
    """

    def __init__(self, cfg: SigningConfig, n: int, crc_extra: Callable[[int], int | None],
                 on_setup_refused: Callable[[int, str], None]):
        self.cfg = cfg
        self.n = n
        self.crc_extra = crc_extra
        self.on_setup_refused = on_setup_refused
        self.key = b""
        self.store: TimestampStore | None = None
        self.tables: list[ReplayTable] = []
        """One replay table per vehicle, for its own endpoint and the GCS endpoint."""
        self.untargeted = ReplayTable(STREAMS_MAX * n, window_10us=None)
        """Frames without a target received on any vehicle endpoint (FleetScope); it rejects
        only what it has seen (no new-stream window: one sender's clock must not shut out
        new streams fleet-wide)."""
        self._target_at: dict[int, int] = {}
        if cfg.mode != "off":
            if not cfg.key_file:
                raise SigningError(f"signing {cfg.mode!r} needs a key file (--signing-key FILE)")
            self.key = load_key(cfg.key_file)
            self.tables = [ReplayTable() for _ in range(n)]
            self._target_at = target_system_offsets(mavlink, swarmdrop)

    def link(self, link_id: int) -> Signing | None:
        """A signing layer with link id link_id and a replay table of its own (None: off)."""
        sc = self.cfg
        if sc.mode == "off":
            return None
        if self.store is None:
            self.store = TimestampStore(sc.timestamp_file or f"{sc.key_file}.timestamp")
        return Signing(sc.mode, self.key, link_id=link_id & 0xFF, store=self.store, crc_extra=self.crc_extra)

    def endpoint(self, k: int | None) -> Signing | None:
        """The signing layer of vehicle k's endpoint, or of the GCS endpoint (k None)."""
        sg = self.link(self.n if k is None else k)
        if sg is not None:
            sg.scope = FleetScope(self.tables, k, self._target_at, untargeted=self.untargeted)
            sg.on_setup_refused = lambda target, reason: self._refused(k, target, reason)
        return sg

    def radio(self) -> Signing | None:
        return self.link(RADIO_LINK_ID)

    def _refused(self, k: int | None, target: int, reason: str) -> None:
        """On the GCS endpoint the target names the vehicle; a broadcast is answered as vehicle 1."""
        if k is None:
            k = target - 1 if 1 <= target <= self.n else 0
        self.on_setup_refused(k, reason)
