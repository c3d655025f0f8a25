"""Fused batch stepper: controller + allocation + rigid body in one numba loop.

Every user of the physics calls ``Physics.step``. The loop runs vehicles in the outer
and physics steps in the inner loop so that a vehicle's state stays in registers; the
per-fleet wind sequence for the call is generated first (from the injected Generator)
so results do not depend on loop order. Nothing is allocated inside the loop.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT
from companion.control import geometric, pid, so3
from companion.control.geometric import N_SP, SP_ACC, SP_POS, SP_Q, max_thrust_n, pack_control_params, pack_setpoint
from companion.params import GRAVITY_MPS2, InnerLoopConfig, VehicleParams
from companion.state import FleetSetpoint, FleetState
from sim_bridge.world.dynamics import VP_G, allocate, motor_coeffs, pack_vehicle_params, rigid_body_step
from sim_bridge.world.jit import compiled
from sim_bridge.world.position_loop import G_STYLE, LOOP_OFF, N_G, N_M, PositionController, position_loop_accel

load_mat, store_mat = compiled(so3.load_mat), compiled(so3.store_mat)
geometric_core, pid_core = compiled(geometric.geometric_core), compiled(pid.pid_core)

CTRL_GEOMETRIC, CTRL_PID = 0, 1


@dataclass(config=STRICT)
class WindConfig:
    """Fleet-wide wind: steady NED vector plus first-order Gauss-Markov gusts per axis
    (the first-order filter of the Dryden model's longitudinal component, with
    correlation time gust_tau_s = L/V, applied to each axis; spatially uniform).

    Wind only acts through the linear drag (VehicleParams.drag_coeff_n_per_mps): a
    scenario with wind and zero drag is refused at load.
    """

    steady_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = Field(default=0.0, ge=0)
    """Stationary standard deviation of each gust component."""
    gust_tau_s: float = Field(default=1.0, gt=0)
    """Correlation time of the Gauss-Markov gust process."""

    @property
    def active(self) -> bool:
        return self.gust_std_mps > 0 or any(v != 0.0 for v in self.steady_ned_mps)


class WindField:
    """One realisation of a WindConfig, sampled at the physics step.

    The SITL shares one field between the Physics of all its parameter groups (one
    wind for the whole fleet, as headless): it calls `advance(n)` once per tick and
    every group steps on `block`.

    Args:
        cfg: the wind.
        dt_s: physics step, s.
        rng: Generator for the gusts (the field's own stream).
    """

    def __init__(self, cfg: WindConfig, dt_s: float, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        sd = cfg.gust_std_mps
        self.gust_ned_mps = rng.normal(0.0, sd, 3) if sd > 0 else np.zeros(3)
        self._phi = math.exp(-dt_s / cfg.gust_tau_s)
        self._sig = sd * math.sqrt(1.0 - self._phi ** 2)
        self.block = np.asarray(cfg.steady_ned_mps, float)[None, :].copy()
        """(n, 3) wind at each step of the current block (or (1, 3) when steady), NED m/s."""

    def advance(self, n_steps: int) -> np.ndarray:
        """Draw the next n_steps of wind into `block` and return it."""
        steady = np.asarray(self.cfg.steady_ned_mps, float)
        if self.cfg.gust_std_mps > 0:
            noise = self.rng.standard_normal((n_steps, 3))
            self.block = _gusts(self.gust_ned_mps, noise, self._phi, self._sig) + steady
        return self.block


def hover_rotor_speed_radps(vp: VehicleParams) -> float:
    """Rotor speed at which the four rotors carry the weight: sqrt(m g / (4 k_f)).

    Raises:
        ValueError: if hover needs more than rotor_speed_max_radps.
    """
    q = math.sqrt(vp.mass_kg * GRAVITY_MPS2 / (4.0 * vp.thrust_coeff_n_per_radps2))
    if q > vp.rotor_speed_max_radps:
        raise ValueError(f"hover rotor speed {q:.0f} rad/s exceeds rotor_speed_max_radps")
    return q


def hover_thrust_norm(vp: VehicleParams) -> float:
    """The collective thrust that carries the vehicle, as a fraction of its maximum (the true
    value of an autopilot's hover-thrust parameter, MPC_THR_HOVER / MOT_THST_HOVER)."""
    return vp.mass_kg * GRAVITY_MPS2 / max_thrust_n(vp)


def hover_state(n: int, vp: VehicleParams, pos_ned_m: np.ndarray | None = None) -> FleetState:
    """N vehicles level, at rest, rotors at hover speed; pos_ned_m (N, 3) or origin."""
    st = FleetState.zeros(n)
    if pos_ned_m is not None:
        st.pos_ned_m[...] = np.asarray(pos_ned_m, float)
    st.rotor_speed_radps[...] = hover_rotor_speed_radps(vp)
    return st


@njit(cache=True)
def _gusts(gust0, noise, phi, sig):
    """Gauss-Markov g_{k+1} = phi g_k + sig n_k; returns (n_steps, 3) values used at step k."""
    out = np.empty_like(noise)
    g0, g1, g2 = gust0[0], gust0[1], gust0[2]
    for k in range(noise.shape[0]):
        out[k, 0], out[k, 1], out[k, 2] = g0, g1, g2
        g0 = phi * g0 + sig * noise[k, 0]
        g1 = phi * g1 + sig * noise[k, 1]
        g2 = phi * g2 + sig * noise[k, 2]
    gust0[0], gust0[1], gust0[2] = g0, g1, g2
    return out


@njit(cache=True)
def _physics_loop(n_steps, active, pos, vel, rot, om, rotor, integ, sp, cprm, vprm, dt, ctrl, mot, wind, ground_z,
                  rotor_scale, acc_ext, loop_gains, loop_mem):
    n_wind = wind.shape[0]
    work = np.empty(sp.shape[1])
    grav = vprm[VP_G]
    for i in range(pos.shape[0]):
        if not active[i]:
            continue
        p = (pos[i, 0], pos[i, 1], pos[i, 2])
        v = (vel[i, 0], vel[i, 1], vel[i, 2])
        r = load_mat(rot, i)
        w = (om[i, 0], om[i, 1], om[i, 2])
        q = (rotor[i, 0], rotor[i, 1], rotor[i, 2], rotor[i, 3])
        xi = (integ[i, 0], integ[i, 1], integ[i, 2], integ[i, 3], integ[i, 4], integ[i, 5])
        de = (acc_ext[i, 0], acc_ext[i, 1], acc_ext[i, 2])
        spi = sp[i]
        # The autopilot's position loops fly position-family setpoints (attitude ones bypass them):
        # the inner controller gets the acceleration they ask for, as the only thing commanded.
        looped = loop_gains[i, G_STYLE] != LOOP_OFF and not math.isfinite(spi[SP_Q])
        lg, lm = loop_gains[i], loop_mem[i]
        if looped:
            for c in range(sp.shape[1]):
                work[c] = spi[c]
            for c in range(6):
                work[SP_POS + c] = math.nan  # (SP_POS..SP_VEL+2: position and velocity)
            spi = work
        s0, s1, s2, s3 = rotor_scale[i, 0], rotor_scale[i, 1], rotor_scale[i, 2], rotor_scale[i, 3]
        healthy = s0 == 1.0 and s1 == 1.0 and s2 == 1.0 and s3 == 1.0
        for k in range(n_steps):
            if looped:
                a = position_loop_accel(p, v, sp[i], lg, lm, dt, grav)
                work[SP_ACC], work[SP_ACC + 1], work[SP_ACC + 2] = a
            if ctrl == CTRL_GEOMETRIC:
                f, m = geometric_core(p, v, r, w, spi, cprm)
            else:
                f, m, xi = pid_core(p, v, r, w, spi, cprm, xi, dt)
            qc = allocate(f, m, vprm)
            if not healthy:  # a failed rotor's command is 0 (sim_bridge.world.faults)
                qc = (qc[0] * s0, qc[1] * s1, qc[2] * s2, qc[3] * s3)
            kw = k if n_wind > 1 else 0
            wd = (wind[kw, 0], wind[kw, 1], wind[kw, 2])
            p, v, r, w, q = rigid_body_step(p, v, r, w, q, qc, vprm, dt, mot, wd, ground_z, de)
        pos[i, 0], pos[i, 1], pos[i, 2] = p
        vel[i, 0], vel[i, 1], vel[i, 2] = v
        store_mat(rot, i, r)
        om[i, 0], om[i, 1], om[i, 2] = w
        rotor[i, 0], rotor[i, 1], rotor[i, 2], rotor[i, 3] = q
        for k in range(6):
            integ[i, k] = xi[k]


_FIELDS = ("pos_ned_m", "vel_ned_mps", "rot_body_to_ned", "omega_body_radps", "rotor_speed_radps", "ctrl_integral")


class Physics:
    """Batch quadrotor physics with the inner-loop controller in the loop.

    Args:
        vehicle: airframe parameters.
        inner: which controller runs every physics step, and its gains.
        dt_s: physics step (s).
        wind: optional WindConfig (acts through drag only), drawn from rng; or a shared
            WindField that its owner advances (then step uses its current block).
        ground_z_m: NED z of a flat ground (vehicles rest on it); None = no ground.
        rng: Generator for the gust noise (required for reproducibility when gusts are on;
            a fixed default_rng(0) is used if omitted).
    Raises:
        ValueError: if dt_s is not positive.
    """

    def __init__(self, vehicle: VehicleParams, inner: InnerLoopConfig, dt_s: float = 0.001,
                 wind: WindConfig | WindField | None = None, ground_z_m: float | None = None,
                 rng: np.random.Generator | None = None):
        if not dt_s > 0:
            raise ValueError("dt_s must be > 0")
        self.vehicle, self.inner, self.dt_s = vehicle, inner, float(dt_s)
        self.ground_z_m = math.inf if ground_z_m is None else float(ground_z_m)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._cprm = pack_control_params(vehicle, inner.geometric, inner.pid)
        self._vprm = pack_vehicle_params(vehicle)
        self._mot = motor_coeffs(vehicle.motor_time_constant_s, self.dt_s)
        self._ctrl = CTRL_GEOMETRIC if inner.controller == "geometric" else CTRL_PID
        self._shared_wind = isinstance(wind, WindField)
        self._ones, self._zeros3 = np.ones((0, 4)), np.zeros((0, 3))
        self._no_gains, self._no_memory = np.zeros((0, N_G)), np.zeros((0, N_M))
        self.wind_field = wind if isinstance(wind, WindField) else WindField(wind or WindConfig(), self.dt_s, self.rng)

    def warm_up(self) -> None:
        """Compile (or load from numba's cache) the stepper now, on a scratch vehicle, so
        that the first real step does not stall a real-time loop for seconds."""
        state = hover_state(1, self.vehicle)
        sp = FleetSetpoint.empty(1)
        sp.pos_ned_m[...] = 0.0
        field, shared = self.wind_field, self._shared_wind
        # the real run's gust sequence stays untouched: a scratch field, held as shared
        self.wind_field, self._shared_wind = WindField(WindConfig(), self.dt_s, np.random.default_rng(0)), True
        try:
            self.step(state, sp, 1)
        finally:
            self.wind_field, self._shared_wind = field, shared

    def _wind_sequence(self, n_steps: int) -> np.ndarray:
        if self._shared_wind:
            block = self.wind_field.block
            if len(block) not in (1, n_steps):
                raise ValueError(f"shared wind block has {len(block)} steps, this step {n_steps}")
            return block
        return self.wind_field.advance(n_steps)

    def step(self, state: FleetState, setpoint: FleetSetpoint | np.ndarray, n_steps: int = 1,
             active: np.ndarray | None = None, rotor_scale: np.ndarray | None = None,
             acc_ext_ned_mps2: np.ndarray | None = None, loop: PositionController | None = None) -> None:
        """Advance every active vehicle n_steps physics steps in place; controller (geometric
        or PID per inner.controller) runs every physics step on the held setpoint. Inactive
        vehicles are untouched.

        Args:
            state: FleetState (N), modified in place.
            setpoint: FleetSetpoint (N), held for the n_steps; or the same already packed
                by geometric.pack_setpoint, (N, N_SP) float64 (a caller that steps several
                groups packs once and hands each its rows).
            active: (N,) bool mask, default all.
            rotor_scale: (N, 4) factor on each rotor's speed command (1 healthy, 0 a failed
                rotor: sim_bridge.world.faults.RotorFaults.scale); default all 1.
            acc_ext_ned_mps2: (N, 3) external acceleration on each vehicle beside gravity and
                drag (an estimator's bias: sim_bridge.world.estimator.bias_disturbance_ned_mps2);
                default none.
            loop: the autopilots' position loops (N rows; sim_bridge.world.position_loop):
                every physics step they turn each position-family setpoint into the
                acceleration the inner controller flies (their memory advances in place);
                default none: the inner controller flies the setpoint itself.
        Raises:
            ValueError: on size mismatch or negative n_steps.
        """
        n = state.n
        if isinstance(setpoint, np.ndarray):
            packed = np.ascontiguousarray(setpoint, np.float64)
            if packed.shape != (n, N_SP):
                raise ValueError(f"packed setpoint has shape {packed.shape}, not ({n}, {N_SP})")
        else:
            if setpoint.n != n:
                raise ValueError(f"setpoint N={setpoint.n} != state N={n}")
            packed = pack_setpoint(setpoint)
        if n_steps < 0:
            raise ValueError("n_steps must be >= 0")
        act = np.ones(n, np.bool_) if active is None else np.ascontiguousarray(active, np.bool_)
        if act.shape != (n,):
            raise ValueError(f"active must have shape ({n},)")
        if n_steps == 0 or n == 0:
            return
        if self._ones.shape[0] != n:
            self._ones, self._zeros3 = np.ones((n, 4)), np.zeros((n, 3))
            self._no_gains, self._no_memory = np.zeros((n, N_G)), np.zeros((n, N_M))
        if rotor_scale is None:
            rotor_scale = self._ones
        elif rotor_scale.shape != (n, 4):
            raise ValueError(f"rotor_scale must have shape ({n}, 4)")
        if acc_ext_ned_mps2 is None:
            acc_ext_ned_mps2 = self._zeros3
        elif acc_ext_ned_mps2.shape != (n, 3):
            raise ValueError(f"acc_ext_ned_mps2 must have shape ({n}, 3)")
        if loop is None:
            gains, memory = self._no_gains, self._no_memory
        else:
            gains, memory = loop.gains, loop.memory
            if gains.shape != (n, N_G) or memory.shape != (n, N_M):
                raise ValueError(f"loop must have {n} rows")
            if not (memory.flags.c_contiguous and memory.dtype == np.float64):
                raise ValueError("loop memory must be a C-contiguous float64 array (it is updated in place)")
        arrays = []
        for name in _FIELDS:
            a = getattr(state, name)
            if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous):
                a = np.ascontiguousarray(a, np.float64)
            arrays.append(a)
        # (numba's stubs type the call by the kernel's parameters; mypy cannot count the arrays in *arrays)
        _physics_loop(int(n_steps), act, *arrays, packed, self._cprm, self._vprm, self.dt_s,  # type: ignore[call-arg]
                      self._ctrl, self._mot, self._wind_sequence(int(n_steps)), self.ground_z_m,
                      np.ascontiguousarray(rotor_scale, np.float64), np.ascontiguousarray(acc_ext_ned_mps2, np.float64),
                      np.ascontiguousarray(gains, np.float64), memory)
        for name, a in zip(_FIELDS, arrays):
            if a is not getattr(state, name):
                getattr(state, name)[...] = a
