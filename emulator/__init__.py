"""Flight-controller side of the cable: vehicle profiles, physics, the gap world, the N3-style flight
controller, the motion-capture system and the radio that forwards it. Never imports `policies`."""

from emulator.kernel_cache import configure as _configure_kernel_cache

_configure_kernel_cache()  # before any kernel module compiles: see emulator.kernel_cache
