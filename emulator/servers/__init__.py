"""The FC's servers on the command link, one per protocol (MAVLink as PX4 speaks it, DJI's OPEN protocol
as an N3 answers it), what they share (telemetry of the vehicle's state, the link's data-rate budget) and
the table of them by protocol name (`emulator.servers.registry`)."""
