"""Default thresholds of `evorobotics.analysis`, in a module without numpy so that the CLI can
show them in `--help` without importing the simulator."""

TOLERANCE_MM = 2.0
"""Default settling tolerance, mm of wheel travel per step: 1/25 of the 50 mm whisker range and
under the +-4.5 mm per step at full speed that the reality gap's +-15 % motor gain spans, so a
difference this small is slip, not a different move."""

RESOLUTION_MM = 1.0
"""Default cell size, mm of wheel travel per step, at which distinct responses are counted."""
