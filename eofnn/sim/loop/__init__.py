"""The plant and the loop: delay, DM (gain, misregistration, nonlinearity), WFS (gain, noise), and the closed-loop
runner that records :class:`~eofnn.telemetry.Telemetry`."""
