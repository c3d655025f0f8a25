"""swarmdrop: the command-line entry point that sees both packages.

``companion`` is the onboard package (the agent and its MAVLink layer) and never
imports ``sim_bridge`` (the simulators and the fleet harness); this tiny package
sits above both so that one ``swarmdrop`` command can offer every subcommand.
"""
