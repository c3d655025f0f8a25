"""Formation shapes: the slot offsets r_k of eq. 25 for a shape, a size and a vehicle count.

`offsets_for(spec, n)` returns (n, 3) offsets from the formation centre, NED metres. Slot k
is row k; which vehicle flies which slot is the plan's slot table (companion.commands,
chosen by companion.control.assignment), so the numbering below only has to be
deterministic.

Axes. Every shape is laid out in its own horizontal axes, **forward** and **right**, then
turned about the vertical by `rotation_rad`: the bearing of the forward axis, clockwise
from north (NED: towards east). rotation 0: forward = north, right = east. A slot at
(forward f, right r, down d) has the NED offset

    (f cos(rot) - r sin(rot),  f sin(rot) + r cos(rot),  d)

* circle (radius_m): a horizontal circle; slot k at bearing 2 pi k / n + rotation
  (slot_order "sequential") or in the mission's interleaved order (below). Centred on the
  circle's centre.
* line (spacing_m): a horizontal line across the direction of travel (along "right"),
  slots spacing_m apart, slot 0 leftmost. Centred on its middle.
* grid (spacing_m): a square grid of ceil(sqrt n) columns, spacing_m apart, rows filled
  front to back and left to right; a partial last row is centred across. Centred on the
  slots' mean.
* wedge (spacing_m): a V with its apex forward: slot 0 at the apex, then alternately the
  left and the right arm, spacing_m apart along each arm, each arm WEDGE_HALF_ANGLE_DEG
  (45 deg) off the backward axis. Centred on the slots' mean.
* shell (radius_m): a sphere (3-D), Fibonacci lattice: slot 0 nearest the top (most
  negative z), heights evenly spaced downwards with k, successive slots turned by the
  golden angle (about 137.5 deg). Centred on the sphere's centre.

The circle reproduces `companion.mission.formation_offsets_ned_m` bit for bit for the
mission's FormationConfig (both slot orders, rotation 0): `spec_from_config` converts one.
"interleaved" (vehicles alternate west and east, filling the circle from its south end) is
a numbering AND, for an odd count, a geometry (its slots are not evenly spaced): it is what
flies today, so a circle always follows the mission's slot_order (companion.commands).
slot_order means nothing for the other shapes and is "sequential" there.

Imports: numpy only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

Shape = Literal["circle", "line", "grid", "wedge", "shell"]
SHAPES: tuple[Shape, ...] = ("circle", "line", "grid", "wedge", "shell")
"""The shapes, in the order of the wire's SWARMDROP_SHAPE values (circle = 0 ... shell = 4)."""
SlotOrder = Literal["sequential", "interleaved"]
WEDGE_HALF_ANGLE_DEG = 45.0
"""Angle of each wedge arm from the backward axis (the V is twice this wide)."""
GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))
RADIUS_SHAPES = frozenset({"circle", "shell"})
"""Shapes sized by radius_m (the others by spacing_m)."""


@dataclass(frozen=True)
class FormationSpec:
    """A formation: shape, size and rotation about the vertical (module docstring).

    Attributes:
        shape: circle, line, grid, wedge or shell.
        radius_m: circle and shell radius, m (> 0; kept, unused, by the other shapes).
        spacing_m: line, grid and wedge spacing, m (> 0; kept, unused, by circle and shell).
        rotation_rad: bearing of the shape's forward axis from north, clockwise, rad.
        slot_order: circle only: "sequential" or the mission's "interleaved" numbering.
    Raises:
        ValueError: unknown shape or slot order, a size not finite and > 0, a rotation not finite.
    """

    shape: Shape = "circle"
    radius_m: float = 40.0
    spacing_m: float = 5.0
    rotation_rad: float = 0.0
    slot_order: SlotOrder = "sequential"

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"unknown formation shape {self.shape!r} (one of {', '.join(SHAPES)})")
        if self.slot_order not in ("sequential", "interleaved"):
            raise ValueError(f"unknown slot order {self.slot_order!r}")
        for name in ("radius_m", "spacing_m"):
            x = getattr(self, name)
            if not (isinstance(x, (int, float)) and math.isfinite(x) and x > 0):
                raise ValueError(f"formation {name} must be a finite number > 0, got {x!r}")
        if not (isinstance(self.rotation_rad, (int, float)) and math.isfinite(self.rotation_rad)):
            raise ValueError(f"formation rotation_rad must be finite, got {self.rotation_rad!r}")

    @property
    def size_m(self) -> float:
        """The size that matters for this shape: radius_m (circle, shell) or spacing_m."""
        return self.radius_m if self.shape in RADIUS_SHAPES else self.spacing_m


class _FormationConfigLike(Protocol):
    @property
    def shape(self) -> str: ...
    @property
    def radius_m(self) -> float: ...
    @property
    def slot_order(self) -> str: ...


def spec_from_config(cfg: _FormationConfigLike) -> FormationSpec:
    """The FormationSpec of a mission's FormationConfig (companion.mission), such that
    `offsets_for(spec_from_config(cfg), n)` equals `formation_offsets_ned_m(cfg, n)` exactly.

    Reads shape, radius_m and slot_order, and spacing_m and rotation_deg when the config
    has them (today's FormationConfig is a circle without either).
    """
    shape = cfg.shape
    spacing = getattr(cfg, "spacing_m", None)
    rotation = getattr(cfg, "rotation_deg", None)
    return FormationSpec(
        shape=shape,  # type: ignore[arg-type]  # (checked by FormationSpec)
        radius_m=float(cfg.radius_m),
        spacing_m=float(spacing) if spacing is not None else FormationSpec.spacing_m,
        rotation_rad=math.radians(rotation) if rotation else 0.0,
        slot_order=cfg.slot_order if shape == "circle" else "sequential",  # type: ignore[arg-type]
    )


def offsets_for(spec: FormationSpec, n: int) -> np.ndarray:
    """The n slot offsets of a formation, (n, 3) NED metres from the formation centre.

    Args:
        spec: shape, size, rotation (module docstring for each geometry).
        n: slots (>= 0; 0 gives an empty (0, 3) array).
    Raises:
        ValueError: n < 0.
    """
    if n < 0:
        raise ValueError(f"slot count must be >= 0, got {n}")
    if n == 0:
        return np.zeros((0, 3))
    if spec.shape == "circle":
        return _circle(spec.radius_m, n, spec.slot_order, spec.rotation_rad)
    if spec.shape == "shell":
        return _shell(spec.radius_m, n, spec.rotation_rad)
    if spec.shape == "line":
        fwd = np.zeros(n)
        right = (np.arange(n) - (n - 1) / 2.0) * spec.spacing_m
    elif spec.shape == "grid":
        fwd, right = _grid(spec.spacing_m, n)
    else:
        fwd, right = _wedge(spec.spacing_m, n)
    return _turn(fwd, right, np.zeros(n), spec.rotation_rad)


def _turn(fwd: np.ndarray, right: np.ndarray, down: np.ndarray, rot: float) -> np.ndarray:
    c, s = math.cos(rot), math.sin(rot)
    return np.stack([fwd * c - right * s, fwd * s + right * c, down], axis=1)


def _circle(r: float, n: int, order: str, rot: float) -> np.ndarray:
    # The same expressions as companion.mission.formation_offsets_ned_m (bit-exact at rot 0:
    # adding 0.0 changes no bearing).
    if order == "sequential":
        bearing = 2.0 * np.pi * np.arange(n) / n
    else:
        i = np.arange(n)
        pairs = (n + 1) // 2
        phi = np.pi * ((i // 2) + 0.5) / pairs  # angle from south, (0, pi)
        side = np.where(i % 2 == 0, -1.0, 1.0)
        bearing = np.pi - side * phi  # from north, clockwise (towards east)
    if rot != 0.0:
        bearing = bearing + rot
    return np.stack([r * np.cos(bearing), r * np.sin(bearing), np.zeros(n)], axis=1)


def _grid(spacing: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    cols = math.ceil(math.sqrt(n))
    k = np.arange(n)
    row, col = k // cols, k % cols
    in_row = np.minimum(cols, n - row * cols)  # slots in each slot's row (the last may be partial)
    fwd = -row * spacing
    right = (col - (in_row - 1) / 2.0) * spacing
    return fwd - fwd.mean(), right


def _wedge(spacing: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    k = np.arange(n)
    along = ((k + 1) // 2) * spacing  # distance from the apex along the arm
    side = np.where(k == 0, 0.0, np.where(k % 2 == 1, -1.0, 1.0))  # odd: left arm, even: right arm
    half = math.radians(WEDGE_HALF_ANGLE_DEG)
    fwd = -along * math.cos(half)
    right = side * along * math.sin(half)
    return fwd - fwd.mean(), right - right.mean()


def _shell(r: float, n: int, rot: float) -> np.ndarray:
    k = np.arange(n)
    h = 1.0 - (2.0 * k + 1.0) / n  # height on the unit sphere, from near +1 (top) to near -1
    rho = np.sqrt(np.maximum(0.0, 1.0 - h * h))
    az = k * GOLDEN_ANGLE_RAD
    return _turn(r * rho * np.cos(az), r * rho * np.sin(az), -r * h, rot)


def min_separation_m(offsets_ned_m: np.ndarray) -> float:
    """Smallest distance between two slots (inf for fewer than two), m."""
    p = np.asarray(offsets_ned_m, dtype=float).reshape(-1, 3)
    if len(p) < 2:
        return math.inf
    d = p[:, None, :] - p[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", d, d))
    dist[np.diag_indices(len(p))] = np.inf
    return float(dist.min())
