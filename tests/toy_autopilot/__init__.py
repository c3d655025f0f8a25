"""A toy third autopilot, defined in two files outside the project's packages: its
companion dialect (dialect.py) and its SITL behaviour (sitl.py). Importing them
registers both (companion.link.registry); tests/test_toy_autopilot.py flies it."""
