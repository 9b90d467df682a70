"""The link layer: transports (serial, pty, UDP, TCP, in-memory) and wire framing. It imports neither
`emulator` nor `policies`: both sides meet only here, as a TX2 meets an N3 over a cable."""
