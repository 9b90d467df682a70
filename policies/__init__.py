"""Onboard-computer side of the cable: motion primitives, gap planning, controllers, networks and the
onboard program that flies a pilot over the links. Never imports `emulator`."""
