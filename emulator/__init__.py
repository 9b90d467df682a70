"""Flight-controller side of the cable: vehicle profiles, physics, the gap world, the N3-style flight
controller, the motion-capture system and the radio that forwards it. Never imports `policies`."""
