"""Replay: a recorded run in the live view, with a playhead the page moves.

Two recordings open:

* a **run directory** (`swarmdrop simulate` or `swarmdrop run`): its telemetry.npz holds the
  true state of every vehicle at the log rate (positions, velocities, attitudes, phases,
  slots, and for a landing mission who is down), its config.json the mission;
* a **.tlog** of the swarm link (what `swarmdrop console --tlog` writes, or a radio
  gateway's log): every SWARMDROP_STATE in it, checked as the live console checks them
  (sysid of the id, phase), resampled on a 10 Hz grid (each vehicle's newest state at or
  before each grid time; one silent for more than 3 s is shown as unknown).

The page asks to play, pause, seek and change speed (swarmdrop.console.protocol); the
playhead moves with the console's clock times the speed and stops at the end.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.config import ConfigError
from swarmdrop.console.live import SIM_BANK_COMPID_BASE, SIM_BANK_SIZE, SIM_BANKS, wire_index
from swarmdrop.console.mission import MissionInfo, mission_of_run
from swarmdrop.console.protocol import Snapshot, yaw_of

SPEEDS = (0.1, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
TLOG_GRID_S = 0.1
TLOG_SILENT_S = 3.0
MAX_SAMPLES = 2_000_000
"""Vehicle-samples a replay holds (T x N); a longer recording is decimated in time."""


@dataclass
class Recording:
    """A recorded run as arrays (T samples, N vehicles).

    Attributes:
        t: (T,) s, increasing.
        pos, vel: (T, N, 3) mission NED; q: (T, N, 4) w, x, y, z; phase, flags: (T, N).
        slot: (T, N, 3) or None; age: (T, N) s since measured; rate: (T, N) states/s or None.
        t_go: (T,) the transit start held then (NaN none), on the same clock as t.
        known: (T, N) bool.
        source: what was opened.
    """

    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    q: np.ndarray
    phase: np.ndarray
    flags: np.ndarray
    slot: np.ndarray | None
    age: np.ndarray
    rate: np.ndarray | None
    t_go: np.ndarray
    known: np.ndarray
    plan_seq: np.ndarray | None
    source: str

    @property
    def n(self) -> int:
        return self.pos.shape[1]

    def snapshot(self, t: float) -> Snapshot:
        """The newest sample at or before t (the first one before the start)."""
        i = max(0, int(np.searchsorted(self.t, t, side="right")) - 1)
        n = self.n
        return Snapshot(
            t=float(self.t[i]), t_go=float(self.t_go[i]), pos=self.pos[i], vel=self.vel[i], yaw=yaw_of(self.q[i]),
            age=self.age[i], slot=self.slot[i] if self.slot is not None else np.full((n, 3), np.nan),
            rate=self.rate[i] if self.rate is not None else np.full(n, np.nan),
            plan_seq=self.plan_seq[i] if self.plan_seq is not None else np.zeros(n, np.uint32),
            phase=self.phase[i], flags=self.flags[i], known=self.known[i])


def _decimate(t: np.ndarray, n: int) -> np.ndarray:
    """Sample indices that keep T x N within MAX_SAMPLES."""
    step = max(1, math.ceil(len(t) * max(n, 1) / MAX_SAMPLES))
    return np.arange(0, len(t), step)


def load_npz(path: Path) -> Recording:
    """telemetry.npz of a run directory.

    Raises:
        ConfigError: not a telemetry file (missing arrays, wrong shapes), or unreadable.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as err:
        raise ConfigError(f"{path}: cannot read it as telemetry.npz: {err}") from None
    need = ("t_s", "pos_ned_m", "vel_ned_mps", "att_q_wxyz", "phase")
    missing = [k for k in need if k not in data]
    if missing:
        raise ConfigError(f"{path}: not a run's telemetry (no {', '.join(missing)})")
    t = np.asarray(data["t_s"], float)
    pos = np.asarray(data["pos_ned_m"], np.float32)
    if pos.ndim != 3 or pos.shape[0] != len(t) or pos.shape[2] != 3 or len(t) == 0:
        raise ConfigError(f"{path}: pos_ned_m has shape {pos.shape} for {len(t)} samples")
    n = pos.shape[1]
    idx = _decimate(t, n)

    def arr(name: str, shape: tuple, dtype) -> np.ndarray | None:
        a = data.get(name)
        if a is None or a.shape[0] != len(t) or a.shape[1:] != shape:
            return None
        return np.asarray(a[idx], dtype)

    vel = arr("vel_ned_mps", (n, 3), np.float32)
    q = arr("att_q_wxyz", (n, 4), np.float32)
    phase = arr("phase", (n,), np.uint8)
    if vel is None or q is None or phase is None:
        raise ConfigError(f"{path}: vel_ned_mps, att_q_wxyz or phase do not match pos_ned_m")
    t = t[idx]
    known = np.ones((len(t), n), bool)
    flags = np.full((len(t), n), 2, np.uint8)  # OWN_VALID: a recorded true state
    return Recording(t=t, pos=pos[idx], vel=vel, q=q, phase=np.minimum(phase, 6), flags=flags,
                     slot=arr("slot_ned_m", (n, 3), np.float32), age=np.zeros((len(t), n), np.float32), rate=None,
                     t_go=_t_go_of_phases(t, phase), known=known, plan_seq=None, source=str(path))


def _t_go_of_phases(t: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """The transit start as a recording shows it: from the first sample with a vehicle in
    TRANSIT on (the page counts from it); NaN before."""
    transit = (phase == 3).any(axis=1)
    out = np.full(len(t), np.nan)
    if transit.any():
        i = int(np.argmax(transit))
        out[i:] = t[i]
    return out


def load_tlog(path: Path, mission: MissionInfo | None) -> Recording:
    """SWARMDROP_STATE frames of a .tlog, resampled (module docstring).

    Raises:
        ConfigError: unreadable, or no valid SWARMDROP_STATE in it.
    """
    from companion.link.enums import MsgId
    from companion.link.framing import FrameError
    from companion.link.msgdef import swarmdrop as sd
    from companion.link.tlog import read_tlog
    from companion.link.wire import Codec
    from companion.swarm import PHASE_COUNT

    codec = Codec(sd)
    at = wire_index(sd.MAVLink_swarmdrop_state_message)
    cap = mission.n if mission is not None and mission.n is not None else SIM_BANKS * SIM_BANK_SIZE
    sysids = mission.sysids if mission is not None and mission.config is not None else None
    rows = []
    try:
        for _, frame in read_tlog(path):
            if len(frame) < 10 or frame[0] != 0xFD or (frame[7] | frame[8] << 8 | frame[9] << 16) != MsgId.SWARMDROP_STATE:
                continue
            try:
                _, sysid, compid, w = codec.decode_raw(frame)
            except FrameError:
                continue
            vid = w[at["vehicle_id"]]
            if SIM_BANK_COMPID_BASE <= compid < SIM_BANK_COMPID_BASE + SIM_BANKS:
                k, ok = vid + (compid - SIM_BANK_COMPID_BASE) * SIM_BANK_SIZE, vid < SIM_BANK_SIZE and sysid == vid + 1
            else:
                k = vid
                ok = sysid == (sysids[k] if sysids is not None and k < len(sysids) else k + 1)
            if not ok or k >= cap or w[at["phase"]] >= PHASE_COUNT:
                continue
            rows.append((k, *w[:16]))
    except OSError as err:
        raise ConfigError(f"{path}: cannot read it: {err.strerror or err}") from None
    if not rows:
        raise ConfigError(f"{path}: no valid SWARMDROP_STATE in this .tlog")
    a = np.array(rows, np.float64)
    ids = a[:, 0].astype(np.int64)
    stamp = a[:, 1] * 1e-6
    t0 = float(stamp.min())
    stamp = stamp - t0
    n = int(ids.max()) + 1 if mission is None or mission.n is None else mission.n
    grid = np.arange(0.0, float(stamp.max()) + TLOG_GRID_S, TLOG_GRID_S)
    grid = grid[_decimate(grid, n)]
    T = len(grid)
    pos = np.full((T, n, 3), np.nan, np.float32)
    vel = np.full((T, n, 3), np.nan, np.float32)
    q = np.tile(np.array([1, 0, 0, 0], np.float32), (T, n, 1))
    phase = np.zeros((T, n), np.uint8)
    flags = np.zeros((T, n), np.uint8)
    plan = np.zeros((T, n), np.uint32)
    age = np.full((T, n), np.nan, np.float32)
    rate = np.zeros((T, n), np.float32)
    known = np.zeros((T, n), bool)
    t_go_v = np.full((T, n), np.nan)
    for k in np.unique(ids).tolist():
        sel = np.flatnonzero(ids == k)
        sel = sel[np.argsort(stamp[sel], kind="stable")]
        st = stamp[sel]
        j = np.searchsorted(st, grid, side="right") - 1
        ok = j >= 0
        jj = np.where(ok, j, 0)
        ok &= grid - st[jj] <= TLOG_SILENT_S
        r = a[sel][jj]
        pos[:, k] = np.where(ok[:, None], r[:, 3:6], np.nan)
        vel[:, k] = np.where(ok[:, None], r[:, 6:9], np.nan)
        q[:, k] = np.where(ok[:, None], r[:, 9:13], q[:, k])
        phase[:, k] = np.where(ok, r[:, 13], 0)
        flags[:, k] = np.where(ok, r[:, 14], 0)
        plan[:, k] = np.where(ok, r[:, 16], 0)
        age[:, k] = np.where(ok, grid - st[jj], np.nan)
        known[:, k] = ok
        go = r[:, 2]
        t_go_v[:, k] = np.where(ok & (go > 0), go * 1e-6 - t0, np.nan)
        rate[:, k] = (np.searchsorted(st, grid, side="right") - np.searchsorted(st, grid - 5.0, side="right")) / 5.0
    bad = ~(np.abs(pos) <= 1e6).all(axis=2)
    pos[bad] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an all-NaN row is a grid time nobody held a t_go)
        t_go = np.nanmedian(t_go_v, axis=1) if np.isfinite(t_go_v).any() else np.full(T, np.nan)
    slot = None
    if mission is not None and mission.config is not None:
        slot = np.full((T, n, 3), np.nan, np.float32)
        for i in range(T):
            s = mission.slots(grid[i] - t_go[i] if math.isfinite(t_go[i]) else -1.0)
            if s is not None:
                slot[i, :len(s)] = s[:n]
    return Recording(t=grid, pos=pos, vel=vel, q=q, phase=phase, flags=flags, slot=slot, age=age, rate=rate,
                     t_go=t_go, known=known, plan_seq=plan, source=str(path))


def open_recording(path: str | Path, mission: MissionInfo | None) -> tuple[Recording, MissionInfo | None]:
    """A run directory, its telemetry.npz, or a .tlog; and the mission to draw with it (the
    given one, else the run directory's config.json).

    Raises:
        ConfigError: nothing replayable there (named, with the reason).
    """
    p = Path(path)
    if p.is_dir():
        npz = p / "telemetry.npz"
        if npz.is_file():
            return load_npz(npz), mission or mission_of_run(p)
        tlogs = sorted(p.glob("*.tlog"))
        if tlogs:
            return load_tlog(tlogs[0], mission), mission
        raise ConfigError(f"{p}: no telemetry.npz or .tlog in this directory (a run directory of swarmdrop "
                          "simulate or swarmdrop run, or a console --tlog)")
    if not p.exists():
        raise ConfigError(f"{p}: no such file or directory")
    if p.suffix == ".npz":
        return load_npz(p), mission or mission_of_run(p.parent)
    return load_tlog(p, mission), mission


class Playhead:
    """Where a replay is: time, play/pause and speed, moved by the console's clock."""

    def __init__(self, rec: Recording, clock=time.monotonic):
        self.rec = rec
        self.clock = clock
        self.t0, self.t1 = float(rec.t[0]), float(rec.t[-1])
        self.t = self.t0
        self.speed = 1.0
        self.playing = False
        self._at = clock()

    def now(self) -> float:
        """The playhead's time now (advancing while playing; it stops at the end)."""
        c = self.clock()
        if self.playing:
            self.t = min(self.t1, self.t + (c - self._at) * self.speed)
            if self.t >= self.t1:
                self.playing = False
        self._at = c
        return self.t

    def play(self) -> None:
        self.now()
        if self.t >= self.t1:
            self.t = self.t0
        self.playing = True

    def pause(self) -> None:
        self.now()
        self.playing = False

    def seek(self, t: float) -> None:
        if not math.isfinite(t):
            raise ValueError("seek: not a number")
        self.now()
        self.t = min(self.t1, max(self.t0, t))

    def set_speed(self, speed: float) -> None:
        if not (math.isfinite(speed) and SPEEDS[0] <= speed <= SPEEDS[-1]):
            raise ValueError(f"speed {speed!r}: from {SPEEDS[0]} to {SPEEDS[-1]}")
        self.now()
        self.speed = float(speed)

    def to_json(self) -> dict:
        return {"t0": self.t0, "t1": self.t1, "t": self.t, "speed": self.speed, "playing": self.playing,
                "speeds": list(SPEEDS), "source": self.rec.source}
