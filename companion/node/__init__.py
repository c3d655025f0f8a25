"""The onboard companion process: one sans-IO Agent flying one vehicle over MAVLink.

Modules: config (what the process is told), vehicle (its autopilot link),
swarmlink (its neighbours), runner (the asyncio loop that ties them to the Agent),
cli (`swarmdrop agent`). Nothing here imports the simulator.
"""
