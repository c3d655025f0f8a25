"""The onboard companion process: one sans-IO Agent flying one vehicle over MAVLink.

Modules: config (what the process is told), vehicle (its autopilot link), swarmlink (its
neighbours), runner (AgentNode: the asyncio process that wires the rest to the Agent),
setup (links, set-up, launch), tick (the control tick: telemetry in, setpoint out),
offboard (the switch to offboard/GUIDED), plan (the setpoint between plans), stats (the
--stats file, typed), exits (exit codes), cli (`swarmdrop agent`). Nothing here imports
the simulator.
"""
