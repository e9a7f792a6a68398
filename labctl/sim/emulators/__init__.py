"""Device emulators that speak the real wire protocols: GRBL 1.1, the robot controller dialect, pty and TCP ports."""
