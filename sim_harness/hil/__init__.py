"""Hardware-in-the-loop emulation of the drone's cameras and autopilot, on their real interfaces."""
