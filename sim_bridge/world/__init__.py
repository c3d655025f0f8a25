"""The simulated world: rigid-body dynamics and the fused physics stepper (eq. 1-6), wind,
the estimator's errors, rotor faults, the carrier, what an autopilot does on its own, and
the neighbour radio model. Imports nothing else of sim_bridge."""
