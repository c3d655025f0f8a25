"""Vehicle and inner-loop controller parameters, with units in every name.

These are validated dataclasses (pydantic) so that they can be loaded from YAML
with errors that name the offending path. The default vehicle is the Bitcraze
Crazyflie 2.0; sources are cited in docs/vehicle.md.
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field
from pydantic.dataclasses import dataclass

from companion.config import STRICT

GRAVITY_MPS2 = 9.80665


@dataclass(config=STRICT)
class VehicleParams:
    """Rigid-body and rotor parameters of one quadrotor.

    frame "x" (default, the real Crazyflie 2.0): rotor k = 1..4 sits at arm_length_m on the
    body diagonals front-right, back-right, back-left, front-left. frame "plus" (the paper's
    eq. 6): rotor k on body axis +x, +y, -x, -y. Rotors 1 and 3 spin clockwise seen from
    above in both (docs/vehicle.md).
    """

    mass_kg: float = Field(default=0.030, gt=0)
    inertia_xx_kgm2: float = Field(default=1.43e-5, gt=0)
    inertia_yy_kgm2: float = Field(default=1.43e-5, gt=0)
    inertia_zz_kgm2: float = Field(default=2.89e-5, gt=0)
    arm_length_m: float = Field(default=0.043, gt=0)
    """Centre-to-rotor distance d."""
    frame: Literal["x", "plus"] = "x"
    thrust_coeff_n_per_radps2: float = Field(default=2.3e-8, gt=0)
    """k_f in eq. 6: rotor thrust = k_f * Q**2."""
    torque_to_thrust_m: float = Field(default=0.0339, gt=0)
    """c_tau_f in eq. 6: rotor reaction torque per newton of thrust."""
    rotor_speed_min_radps: float = Field(default=0.0, ge=0)
    rotor_speed_max_radps: float = Field(default=2500.0, gt=0)
    motor_time_constant_s: float = Field(default=0.072, ge=0)
    """First-order motor lag; 0 means instantaneous rotors."""
    drag_coeff_n_per_mps: float = Field(default=0.0, ge=0)
    """Linear translational drag, F = -c * (v - wind). Zero by default (do-nothing default)."""


@dataclass(config=STRICT)
class GeometricGains:
    """Gains of the geometric SE(3) controller, eq. 9 and eq. 14, normalised.

    Translational gains are per unit mass (k_x = mass * kx_per_s2) and rotational
    gains per unit inertia (k_R = J * kR_per_s2, diagonal), so the same numbers fit
    any airframe. See docs/controllers.md.
    """

    kx_per_s2: float = Field(default=4.0, ge=0)
    kv_per_s: float = Field(default=4.0, ge=0)
    kR_per_s2: float = Field(default=200.0, gt=0)
    kOmega_per_s: float = Field(default=28.0, gt=0)
    tilt_max_deg: float = Field(default=50.0, gt=0, le=89.0)
    acc_max_mps2: float = Field(default=12.0, gt=0)
    """Norm limit on the commanded acceleration before thrust/tilt saturation."""
    large_angle: bool = True
    """Tilt-first attitude error that does not vanish near 180 deg, and thrust scheduled by
    where body z points (docs/controllers.md, "Large angles"); False flies the paper's
    eq. 7-14 verbatim. The two agree to first order near hover."""
    yaw_error_max_rad: float = Field(default=0.6, gt=0)
    """Large-angle law: the yaw part of the attitude error is clipped to this."""


@dataclass(config=STRICT)
class PIDGains:
    """Integral pole placement of the PID baseline; the P and D terms are derived
    from GeometricGains so that both controllers share their small-angle poles.

    The velocity integrator is off by default: through the finite-bandwidth
    attitude loop it moves the horizontal poles by up to 15 % (docs/controllers.md),
    and it pulls a launched vehicle back towards its release point, so the
    geometric-vs-PID comparison would no longer isolate large-angle behaviour.
    """

    att_integral_pole_per_s: float = Field(default=2.0, ge=0)
    vel_integral_pole_per_s: float = Field(default=0.0, ge=0)


@dataclass(config=STRICT)
class InnerLoopConfig:
    """Which inner-loop controller flies (the simulators run it every physics step), with the
    gains of both, so that the launch studies can compare them on one scenario. In the SITL
    these are the defaults of the vehicles' parameters (SD_GEO_*, the tilt limit).

    Raises:
        pydantic.ValidationError: an unknown controller or a gain out of range.
    """

    controller: Literal["geometric", "pid"] = "geometric"
    geometric: GeometricGains = GeometricGains()
    pid: PIDGains = PIDGains()
