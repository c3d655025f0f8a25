"""Multi-vehicle PX4-flavoured MAVLink 2 SITL (`swarmdrop sitl`). See docs/sitl.md."""
