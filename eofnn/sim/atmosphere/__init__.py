"""The atmosphere: turbulence models (exact frozen flow on lattice and any winds, HCIPy's pupil layer, the B-spline
strip), changing conditions, vibrations and boiling. Each yields ``s(n)`` on the actuators through a sensing kernel
(:mod:`eofnn.sim.sensing`)."""
